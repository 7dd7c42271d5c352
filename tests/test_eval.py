import json
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import torch

from salad.cli import main
from salad.data.captions import caption_line, captions_for
from salad.data.dataset import MotionDataset
from salad.eval import metrics as M
from salad.eval.classifiers import load_classifier
from salad.eval.evaluator import Evaluator, load_evaluator
from salad.data.labels import side_of
from salad.eval.physics import batch_physical_checks, physical_checks, physical_checks_features
from salad.eval.t2m import evaluate_t2m, ground_truth_generator, write_report
from salad.training.classifier_task import ClassifierTask, ClassifierTrainConfig, train_classifier
from salad.training.evaluator_task import EvaluatorTask, EvaluatorTrainConfig, load_config
from salad.motion import features_to_joints, joints_to_features, mirror_joints
from salad.motion.representation import feature_statistics
from salad.training.loop import Trainer
from tests.conftest import synthetic_walk

# --------------------------------------------------------------------------- metrics: known answers


def test_fid_of_identical_and_shifted_gaussians():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 8)) @ rng.normal(size=(8, 8))
    assert M.fid(x, x) == pytest.approx(0.0, abs=1e-6)
    shift = np.array([3.0, -1.0, 0, 0, 0, 0, 0, 2.0])
    assert M.fid(x, x + shift) == pytest.approx(float(shift @ shift), rel=1e-6)
    # diagonal Gaussians: sum of squared mean and standard-deviation differences
    mu1, mu2 = np.zeros(3), np.ones(3)
    s1, s2 = np.diag([1.0, 4.0, 9.0]), np.diag([4.0, 4.0, 1.0])
    assert M.frechet_distance(mu1, s1, mu2, s2) == pytest.approx(3 + 1 + 0 + 4, rel=1e-9)


def test_fid_survives_singular_covariances():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(5, 16)), rng.normal(size=(5, 16))  # rank 4 < 16
    v = M.fid(a, b)
    assert np.isfinite(v) and v > 0
    with pytest.raises(ValueError, match="NaN"):
        M.fid(np.full((4, 2), np.nan), a[:, :2])


def test_r_precision_known_answers():
    e = np.eye(32) * 5
    np.testing.assert_allclose(M.r_precision(e, e), [1, 1, 1])
    # motions on a line, each text 0.6 past its motion: the next motion is nearer, except for the last one
    motions = np.arange(32, dtype=float)[:, None]
    texts = motions + 0.6
    np.testing.assert_allclose(M.r_precision(texts, motions), [1 / 32, 1, 1])
    # a collapsed space (all equal) never counts as a hit
    np.testing.assert_allclose(M.r_precision(np.zeros((32, 4)), np.zeros((32, 4))), [0, 0, 0])
    # pools: the second pool of 32 is all wrong (rolled), so the average halves
    both = np.concatenate([e, e])
    rolled = np.concatenate([e, np.roll(e, 1, axis=0)])
    np.testing.assert_allclose(M.r_precision(both, rolled)[0], 0.5)
    with pytest.raises(ValueError, match="fewer rows"):
        M.r_precision(e[:10], e[:10])


def test_distances_diversity_multimodality_and_ci():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 6))
    d = rng.normal(size=6)
    assert M.matching_distance(x + d, x) == pytest.approx(np.linalg.norm(d))
    np.testing.assert_allclose(M.pairwise_distances(x[:5], x[:7]),
                               np.linalg.norm(x[:5, None] - x[None, :7], axis=-1), atol=1e-9)
    div = M.diversity(x, 300, np.random.default_rng(3))
    assert M.diversity(2 * x + d, 300, np.random.default_rng(3)) == pytest.approx(2 * div)
    assert M.diversity(np.ones((400, 6)), 300) == 0.0
    # two independent standard normals in 6-d: E||a - b|| is close to sqrt(12)
    assert div == pytest.approx(np.sqrt(12), rel=0.1)
    same = np.repeat(rng.normal(size=(10, 1, 4)), 30, axis=1)
    assert M.multimodality(same, 10) == 0.0
    spread = same + rng.normal(size=same.shape)
    mm = M.multimodality(spread, 10, np.random.default_rng(0))
    assert M.multimodality(3 * spread, 10, np.random.default_rng(0)) == pytest.approx(3 * mm)
    mean, ci = M.mean_ci([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and ci == pytest.approx(1.96 * np.sqrt(1.25) / 2)


# --------------------------------------------------------------------------- physics


def test_physics_speed_turn_and_mirror():
    walk = synthetic_walk(frames=81, speed=1.2)
    feats = joints_to_features(walk)
    checks = physical_checks_features(feats)
    assert checks["root_speed_mps"] == pytest.approx(1.2, rel=0.05)
    assert abs(checks["turn_deg"]) < 5
    left = synthetic_walk(frames=81, speed=1.2, turn=0.5)  # 0.5 rad/s for 4 s, towards +X
    turn = physical_checks(left)["turn_deg"]
    assert turn == pytest.approx(np.degrees(0.5 * 3.8), abs=3)  # ends averaged over 5 frames: 3.8 s apart
    mirrored = physical_checks(mirror_joints(left))
    assert mirrored["turn_deg"] == pytest.approx(-turn, abs=1e-6)
    # the same through the features, as generated motions arrive
    assert physical_checks(features_to_joints(joints_to_features(left)))["turn_deg"] > 80
    # mirroring swaps the wrists
    plain = physical_checks(left)
    assert mirrored["left_wrist_path_m"] == pytest.approx(plain["right_wrist_path_m"], rel=1e-6)
    assert mirrored["right_wrist_height_m"] == pytest.approx(plain["left_wrist_height_m"], rel=1e-6)


def test_physics_floor_and_skating():
    pose = np.repeat(synthetic_walk(frames=2)[:1], 40, axis=0)
    pose[..., 1] -= pose[..., 1].min()  # lowest joint exactly on the floor
    pose[:, [10, 11], 1] = [0.0, 0.01]  # toes planted
    still = physical_checks(pose)
    assert still["foot_skating_ratio"] == 0.0 and still["root_speed_mps"] == 0.0
    assert still["penetration_m"] == 0.0 and still["floating_m"] == pytest.approx(0.0, abs=1e-6)
    slide = pose + (np.arange(40)[:, None, None] / 20.0) * np.array([0.0, 0.0, 1.0])  # 1 m/s, feet down
    assert physical_checks(slide)["foot_skating_ratio"] == 1.0
    sunk = physical_checks(pose - np.array([0.0, 0.1, 0.0]))
    assert sunk["max_penetration_m"] == pytest.approx(0.1, abs=1e-6)
    lifted = physical_checks(pose + np.array([0.0, 0.2, 0.0]))
    assert lifted["floating_m"] == pytest.approx(0.2, abs=1e-6)
    assert still["acceleration_mps2"] == 0.0 and physical_checks(slide)["acceleration_mps2"] == pytest.approx(0, abs=1e-6)
    jitter = pose + np.random.default_rng(0).normal(scale=0.01, size=pose.shape)
    assert physical_checks(jitter)["acceleration_mps2"] > 5.0  # 1 cm noise at 20 fps: ~ 400 * 0.01 * sqrt(6)
    batch = batch_physical_checks([pose, slide], features=False)
    np.testing.assert_allclose(batch["foot_skating_ratio"], [0.0, 1.0])
    with pytest.raises(ValueError, match="shape"):
        physical_checks(np.zeros((10, 21, 3)))


def test_side_labels_follow_mirroring():
    assert side_of("bye", False) == "right" and side_of("bye", True) == "left"
    # wave-left-hand's mirror copy is already labelled wave-right-hand
    assert side_of("wave-right-hand", True) == "right"
    assert side_of("walk-turn-left", False) == "left" and side_of("run", True) == "none"
    assert side_of("byebye", True) == "both"


# --------------------------------------------------------------------------- tiny dataset + models

KINDS = [  # content, style, turn (rad/s), speed (m/s)
    ("walk", "normal", 0.0, 1.2), ("walk-turn-left", "normal", 0.6, 1.2), ("walk-turn-right", "happy", -0.6, 1.2),
    ("run", "happy", 0.0, 2.8),
]


@pytest.fixture(scope="module")
def labelled_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tiny-hml")
    (root / "new_joint_vecs").mkdir()
    (root / "texts").mkdir()
    labels, splits, feats = {}, {"train": [], "val": [], "test": []}, []
    for i in range(36):
        content, style, turn, speed = KINDS[i % len(KINDS)]
        name = f"m{i:03d}"
        f = joints_to_features(synthetic_walk(frames=30 + 3 * i, seed=i, speed=speed, turn=turn))
        np.save(root / "new_joint_vecs" / f"{name}.npy", f)
        feats.append(f)
        caps = captions_for(content, style, name)
        (root / "texts" / f"{name}.txt").write_text("\n".join(caption_line(c) for c in caps) + "\n")
        split = "train" if i < 20 else ("val" if i < 28 else "test")
        splits[split].append(name)
        labels[name] = {"dataset": 2, "content": content, "style": style, "mirrored": False, "source": "synthetic",
                        "split": split}
    for s, names in splits.items():
        (root / f"{s}.txt").write_text("\n".join(names) + "\n")
    mean, std = feature_statistics(np.concatenate(feats))
    np.save(root / "Mean.npy", mean)
    np.save(root / "Std.npy", std)
    (root / "labels.json").write_text(json.dumps(labels))
    return root


@pytest.fixture(scope="module")
def minilm():
    from salad.models.text import load_text_encoder
    return load_text_encoder("minilm")


TINY_MODEL = """
[model.motion]
conv_channels = 32
gru_hidden = 32
output_dim = {out}
"""


def _write_config(path: Path, root: Path, out_dir: Path, text: str, steps: int = 4,
                  head: str = "val_pool = 4") -> Path:
    path.write_text(f"""
{head}
[data]
root = "{root}"
{text}
[optim]
batch_size = 8
max_steps = {steps}
warmup_steps = 2

[run]
out_dir = "{out_dir}"
bf16 = false
threads = 1
checkpoint_every = {steps}
log_every = 2
""")
    return path


def test_evaluator_trains_saves_and_loads_bit_exactly(labelled_dataset, minilm, tmp_path):
    cfg_file = _write_config(tmp_path / "ev.toml", labelled_dataset, tmp_path / "run",
                             TINY_MODEL.format(out=16) + "[model.text]\ngru_hidden = 16\noutput_dim = 16\n")
    cfg = load_config(Namespace(config=cfg_file, out_dir=None, max_steps=None, data=None))
    assert isinstance(cfg, EvaluatorTrainConfig) and cfg.optim.max_steps == 4
    task = EvaluatorTask(cfg, text_encoder=minilm, progress=False)
    out = Trainer(task, cfg.optim, cfg.run).fit()
    ev = load_evaluator(out, minilm)
    trained = task.model.state_dict()
    loaded = ev.matcher.state_dict()
    assert trained.keys() == loaded.keys()
    assert all(torch.equal(trained[k], loaded[k]) for k in trained)
    ds = MotionDataset(labelled_dataset, "test", max_frames=10 ** 9)
    motions = [it.features for it in ds.items]
    fresh = Evaluator(task.model, ev.mean, ev.std, minilm)
    np.testing.assert_array_equal(ev.embed_motions(motions), fresh.embed_motions(motions))
    emb = ev.embed_motions(motions)
    assert emb.shape == (len(motions), 16)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    # a motion's embedding does not depend on the batch it is embedded with
    np.testing.assert_allclose(ev.embed_motions(motions[:1]), emb[:1], atol=1e-5)
    texts = ev.embed_texts(ds.items[0].captions)
    assert texts.shape == (len(ds.items[0].captions), 16) and np.isfinite(texts).all()
    assert (tmp_path / "run" / "val.jsonl").is_file()
    with pytest.raises(ValueError, match="expected shape"):
        ev.embed_motions([np.zeros((20, 259))])
    with pytest.raises(ValueError, match="frames"):
        ev.embed_motions([np.zeros((3, 263))])

    # the ground-truth row of the protocol on the tiny test split
    res = evaluate_t2m(ground_truth_generator(ds), ds, ev, repeats=2, batch_size=4, mm_prompts=3, mm_repeats=4)
    for key in ("R_precision_top1", "R_precision_top2", "R_precision_top3", "FID", "MM_Dist", "Diversity"):
        m = res["metrics"][key]
        assert np.isfinite(m["mean"]) and np.isfinite(m["ci95"]) and len(m["values"]) == 2
    assert "MultiModality" not in res["metrics"]  # not defined for real motions
    assert res["metrics"]["R_precision_top3"]["mean"] >= res["metrics"]["R_precision_top1"]["mean"]
    assert res["protocol"]["motions_per_repeat"] == 8

    # a stochastic generator gets MultiModality; lengths and shapes are checked
    base = ds.items[0].features

    def jitter(captions, lengths, rng=np.random.default_rng(0)):
        return [np.resize(base, (n, 263)) + 0.05 * rng.normal(size=(n, 263)).astype(np.float32) for n in lengths]

    res2 = evaluate_t2m(jitter, ds, ev, repeats=2, batch_size=4, mm_prompts=3, mm_repeats=4)
    assert res2["metrics"]["MultiModality"]["mean"] > 0
    assert res2["metrics"]["FID"]["mean"] > res["metrics"]["FID"]["mean"]
    with pytest.raises(ValueError, match="shape"):
        evaluate_t2m(lambda c, n: [np.zeros((k + 1, 263)) for k in n], ds, ev, repeats=1, batch_size=4, mm_prompts=0)

    # generation batches are grouped by length, and each motion is scored against its own caption
    ids = {c: k for k, c in enumerate(sorted({c for it in ds.items for c in it.captions}))}
    calls = []

    def tagged(captions, lengths):
        calls.append(list(lengths))
        return [np.full((n, 263), ids[c], np.float32) for c, n in zip(captions, lengths)]

    class Spy:
        def __init__(self):
            self.texts, self.motions = [], []

        def embed_texts(self, captions):
            self.texts.append(list(captions))
            return ev.embed_texts(captions)

        def embed_motions(self, motions):
            self.motions.append(list(motions))
            return ev.embed_motions(motions)

    spy = Spy()
    evaluate_t2m(tagged, ds, spy, repeats=1, batch_size=4, mm_prompts=0)
    assert sum(map(len, calls)) == 8 and all(max(a) <= min(b) for a, b in zip(calls, calls[1:]))
    scored, captions = spy.motions[1], spy.texts[0]     # [0] is the reference set
    assert [int(m[0, 0]) for m in scored] == [ids[c] for c in captions]
    report = write_report({"Real motion": res, "Jitter": res2}, tmp_path / "report")
    text = report.read_text()
    assert "| Real motion |" in text and "| Jitter |" in text and "MultiModality" in text
    assert "generated in batches of similar length" in text
    assert set(json.loads((tmp_path / "report" / "results.json").read_text())) == {"Real motion", "Jitter"}


def test_classifier_trains_saves_and_loads(labelled_dataset, tmp_path):
    cfg_file = _write_config(tmp_path / "clf.toml", labelled_dataset, tmp_path / "clf", TINY_MODEL.format(out=16),
                             head="")
    assert train_classifier(Namespace(config=cfg_file, out_dir=None, max_steps=None, data=None)) == 0
    clf = load_classifier(tmp_path / "clf" / "model")
    assert clf.classes["content"] == ["run", "walk", "walk-turn-left", "walk-turn-right"]
    assert clf.classes["side"] == ["none", "left", "right"]
    summary = json.loads((tmp_path / "clf" / "summary.json").read_text())
    assert set(summary["test"]) == {"content", "style", "side"} and isinstance(summary["warnings"], list)
    assert 0 <= summary["test"]["content"]["accuracy"] <= 1
    for split, n in (("train", 20), ("val", 8), ("test", 8)):      # every motion counted once per head
        classes = summary[split]["content"]["classes"]
        assert summary[split]["content"]["n"] == n == sum(c["n"] for c in classes.values())
        right = n - sum(sum(c["wrong"].values()) for c in classes.values())
        assert right == round(summary[split]["content"]["accuracy"] * n)
    # the same through `salad eval-classifier`, with its report
    assert main(["eval-classifier", "--data", str(labelled_dataset), "--classifier", str(tmp_path / "clf" / "model"),
                 "--splits", "train, test", "--out", str(tmp_path / "ev")]) == 0
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["test"] == summary["test"] and "val" not in res
    assert "| train | 20 |" in (tmp_path / "ev" / "report.md").read_text()
    assert main(["eval-classifier", "--data", str(labelled_dataset), "--splits", "dev", "--out", str(tmp_path / "x")]) == 2
    ds = MotionDataset(labelled_dataset, "test", max_frames=10 ** 9)
    feats = [it.features for it in ds.items]
    pred = clf.predict(feats)
    assert len(pred["content"]) == len(feats) and set(pred["side"]) <= {"none", "left", "right"}
    assert pred["style_probs"].shape == (len(feats), 2)
    np.testing.assert_allclose(pred["content_probs"].sum(1), 1.0, atol=1e-5)
    again = load_classifier(tmp_path / "clf" / "model").predict(feats)
    np.testing.assert_array_equal(again["content_probs"], pred["content_probs"])


def test_a_class_called_something_else_in_most_of_its_motions_is_named():
    from salad.training.classifier_task import misread_classes

    lines = misread_classes({"kick": {"n": 2, "wrong": {"punch": 2}}, "walk": {"n": 300, "wrong": {"run": 3}},
                             "bow": {"n": 4, "wrong": {"guide": 2}}})
    assert lines == ["kick: 2 of its 2 training motions are called punch (2)"]


def test_classifier_learns_the_turn_direction(labelled_dataset):
    """A few dozen steps on the synthetic walks separate left turns, right turns and straight walks."""
    cfg = ClassifierTrainConfig()
    cfg.data.root = str(labelled_dataset)
    cfg.model.motion.conv_channels = cfg.model.motion.gru_hidden = 32
    cfg.model.motion.output_dim = 32
    cfg.optim.batch_size, cfg.optim.warmup_steps, cfg.optim.lr = 16, 5, 3e-3
    task = ClassifierTask(cfg)
    torch.manual_seed(0)
    opt = torch.optim.AdamW(task.model.parameters(), lr=3e-3)
    rng = np.random.default_rng(0)
    for _ in range(40):
        loss, _ = task.model(task.batch(rng))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert task.validate(task.model)["side"] >= 0.75


def test_model_and_vae_rows_of_the_protocol(labelled_dataset, minilm, tiny_model, tmp_path):
    from salad.eval.generators import ModelGenerator, VAEReconstruction
    from salad.pipeline import load_pipeline
    cfg_file = _write_config(tmp_path / "ev.toml", labelled_dataset, tmp_path / "run",
                             TINY_MODEL.format(out=16) + "[model.text]\ngru_hidden = 16\noutput_dim = 16\n")
    cfg = load_config(Namespace(config=cfg_file, out_dir=None, max_steps=None, data=None))
    ev = load_evaluator(Trainer(EvaluatorTask(cfg, text_encoder=minilm, progress=False), cfg.optim, cfg.run).fit(),
                        minilm)
    ds = MotionDataset(labelled_dataset, "test", max_frames=40)
    pipe = load_pipeline(tiny_model)
    gen = ModelGenerator(pipe, steps=3)
    res = evaluate_t2m(gen, ds, ev, repeats=2, batch_size=4, mm_prompts=2, mm_repeats=6, max_frames=40)
    assert np.isfinite(res["metrics"]["FID"]["mean"]) and gen.calls >= 4
    assert res["metrics"]["MultiModality"]["mean"] > 0
    # an interrupted run resumes after its finished repeats and ends where an uninterrupted one does
    state = tmp_path / "partial" / "model.json"
    kw = dict(batch_size=4, mm_prompts=2, mm_repeats=6, max_frames=40, state_file=state)
    evaluate_t2m(ModelGenerator(pipe, steps=3), ds, ev, repeats=1, **kw)
    assert len(json.loads(state.read_text())["repeats"]) == 1
    resumed_gen = ModelGenerator(pipe, steps=3)
    resumed = evaluate_t2m(resumed_gen, ds, ev, repeats=2, **kw)
    assert resumed_gen.calls == gen.calls
    for name, m in res["metrics"].items():
        assert np.allclose(resumed["metrics"][name]["values"], m["values"], rtol=1e-5), name
    other = evaluate_t2m(ModelGenerator(pipe, steps=4), ds, ev, repeats=1, **kw)   # another generator: no reuse
    assert other["metrics"]["FID"]["values"][0] != res["metrics"]["FID"]["values"][0]
    vae = VAEReconstruction(pipe)
    rec = evaluate_t2m(vae, ds, ev, repeats=1, batch_size=4, mm_prompts=0, max_frames=40)
    assert np.isfinite(rec["metrics"]["FID"]["mean"]) and 0 < vae.mpjpe_m < 2.0
