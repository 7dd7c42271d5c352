"""The fidelity benchmark: held-out prompts, per-class measures, stated rules, a real run."""
import json

import pytest

from conftest import synthetic_walk, write_tiny_dataset
from salad.data.captions import CONTENT_PHRASES, STYLE_PHRASES, caption_variants
from salad.eval import EMBEDDED_CLASSIFIER
from salad.eval.classifiers import load_classifier
from salad.eval.fidelity import (RULES, checks_for, evaluate_fidelity, fidelity_classes, judge, measure, named_side,
                                 rejudge, report_markdown)
from salad.eval.paraphrases import HELD_OUT, PROMPT_SETS
from salad.pipeline import load_pipeline


def test_held_out_paraphrases_are_never_training_captions():
    captions = {c.lower() for content in CONTENT_PHRASES for style in STYLE_PHRASES
                for c, _ in caption_variants(content, style)}
    assert set(PROMPT_SETS["b"]) == set(HELD_OUT), "both sets prompt every class"
    for held_out in PROMPT_SETS.values():
        for key, prompts in held_out.items():
            content, _, style = key.partition("/")
            assert content in CONTENT_PHRASES and (not style or style in STYLE_PHRASES), key
            assert len(set(prompts)) >= 2, key
            for p in prompts:
                assert p.lower() not in captions, f"{p!r} is a training caption"
    assert {c.prompts for c in fidelity_classes(["walk"], "b")} == {PROMPT_SETS["b"]["walk"]}
    with pytest.raises(ValueError, match="unknown prompt set"):
        fidelity_classes(prompt_set="c")


def test_every_check_has_a_stated_rule():
    for cls in fidelity_classes():
        assert set(cls.checks) <= set(RULES), cls.key
    with pytest.raises(ValueError, match="unknown fidelity classes"):
        fidelity_classes(["walk", "cartwheel"])
    assert "leg_lift_m" in checks_for("kick") and "side" in checks_for("wave-left-hand")
    assert "still_foot_share" in checks_for("walk-turn-left")


def test_measures_read_a_walk_as_a_walk():
    m = measure(synthetic_walk(80, speed=1.2))
    assert m["duration_s"] == pytest.approx(4.0)
    assert 1.0 < m["root_speed_mps"] < 1.4
    assert abs(m["turn_deg"]) < 15
    turning = measure(synthetic_walk(80, turn=0.6))
    assert turning["turn_deg"] > 60                              # a left turn is positive
    assert 0.0 <= m["still_foot_share"] <= 1.0 and m["jerk_mps3"] > 0


def test_rules_pass_and_fail_where_stated():
    real = [{"duration_s": 4.0, "leg_lift_m": 1.0, "still_foot_share": 0.9, "side": "right"}] * 3
    assert judge("duration_s", real, [{"duration_s": 5.3}])["pass"]
    assert not judge("duration_s", real, [{"duration_s": 5.5}])["pass"]
    assert judge("leg_lift_m", real, [{"leg_lift_m": 0.71}])["pass"]
    assert not judge("leg_lift_m", real, [{"leg_lift_m": 0.3}])["pass"]
    planted = [{"still_foot_share": 0.8}]
    assert judge("still_foot_share", real, planted)["pass"]                      # >= 0.8 x 0.9 raw
    assert not judge("still_foot_share", real, planted, cleaned=True)["pass"]   # < 0.95 x 0.9 cleaned
    sides = [{"side": "right"}, {"side": "right"}, {"side": "left"}]
    assert judge("side", real, sides)["pass"] and not judge("side", real, sides[1:])["pass"]


def test_a_checks_margin_is_its_distance_inside_the_rule():
    """The margin (a checkpoint's validation score reads it) is >= 0 exactly where the check passes, grows
    with the distance inside the rule as a share of its tolerance, and is clipped to [-1, 1]."""
    real = [{"duration_s": 4.0, "root_speed_mps": 1.0, "turn_deg": 90.0, "hand_height_m": 1.5, "leg_lift_m": 1.0,
             "bow_depth_m": 0.5, "still_foot_share": 0.9, "jerk_mps3": 10.0, "side": "right"}] * 3
    for check, values in (("duration_s", (2.0, 2.6, 4.0, 5.4, 5.5, 9.0)), ("root_speed_mps", (0.5, 0.75, 1.0, 1.31)),
                          ("turn_deg", (0.0, 54.0, 90.0, 126.5)), ("hand_height_m", (1.2, 1.36, 1.5, 1.66)),
                          ("leg_lift_m", (0.0, 0.69, 0.7, 1.4, 3.0)), ("bow_depth_m", (0.1, 0.3, 0.9)),
                          ("still_foot_share", (0.5, 0.72, 1.0)), ("jerk_mps3", (5.0, 20.0, 20.5, 60.0))):
        judged = [judge(check, real, [{check: v}]) for v in values]
        for v, j in zip(values, judged):
            assert (j["margin"] >= 0) == j["pass"] and -1.0 <= j["margin"] <= 1.0, (check, v, j)
        assert any(j["pass"] for j in judged) and not all(j["pass"] for j in judged), check
    assert judge("leg_lift_m", real, [{"leg_lift_m": 1.4}])["margin"] == pytest.approx(1.0)
    assert judge("leg_lift_m", real, [{"leg_lift_m": 0.35}])["margin"] == pytest.approx(-0.5)
    assert judge("duration_s", real, [{"duration_s": 4.0}])["margin"] == pytest.approx(1.0)
    assert judge("side", real, [{"side": "right"}] * 3)["margin"] == pytest.approx(0.5, abs=1e-6)
    assert judge("side", real, [{"side": "left"}] * 3)["margin"] == pytest.approx(-1.0)


def test_the_side_check_asks_for_the_hand_the_prompt_names():
    assert named_side("someone waves the Right hand to part") == "right"
    assert named_side("a person waves goodbye using both arms") == named_side("says goodbye waving two hands") == "both"
    assert named_side("a person waves") is None and named_side("from the left hand to the right") is None
    # a class whose captures come with their mirror images: as many left-handed real clips as right
    mirrored = [{"side": "left"}, {"side": "right"}] * 2
    right = [{"side": "right"}] * 3
    asked = judge("side", mirrored, right, sides=["right"] * 3)
    assert asked["pass"] and asked["real"] == "right"
    assert not judge("side", mirrored, right, sides=["left"] * 3)["pass"]
    # a prompt that names no hand is held to the real clips' majority
    lefty = [{"side": "left"}] * 3
    assert not judge("side", lefty, right, sides=[None] * 3)["pass"]
    assert judge("side", lefty, [{"side": "left"}] * 3, sides=[None] * 3)["pass"]


@pytest.mark.slow
def _walks_labelled(tmp_path):
    """The tiny dataset with every motion labelled a normal walk."""
    root = write_tiny_dataset(tmp_path / "data")
    split = {n: f for f in ("train", "val", "test") for n in (root / f"{f}.txt").read_text().split()}
    (root / "labels.json").write_text(json.dumps(
        {n: {"content": "walk", "style": "normal", "split": s} for n, s in split.items()}))
    return root


def test_a_fidelity_run_with_the_embedded_model(tmp_path):
    root = _walks_labelled(tmp_path)
    clf = load_classifier(EMBEDDED_CLASSIFIER)
    res = evaluate_fidelity(load_pipeline(), root, seeds=1, steps=4, classes=["walk", "kick"], classifier=clf)
    (row,) = res["rows"]                                        # kick has no clips in this dataset
    assert row["class"] == "walk" and row["reference"]["clips"] == 12 and row["reference"]["splits"] == "all"
    assert len(row["reference"]["measures"]) == 12                      # 2 test clips only: all splits
    assert set(row["samples"][0]["raw"]) == set(row["samples"][0]["clean"]) >= set(checks_for("walk"))
    assert len(row["samples"]) == len(HELD_OUT["walk"])
    for variant in ("raw", "clean"):
        assert set(row[variant]["checks"]) == set(checks_for("walk"))
        assert row[variant]["pass"] == all(c["pass"] for c in row[variant]["checks"].values())
    # the foot lock changes only the feet: durations and the root path stay the same
    assert row["raw"]["checks"]["duration_s"] == row["clean"]["checks"]["duration_s"]
    # the classifier's verdict on every generated motion, counted per class and overall
    got = row["classified"]
    assert got["total"] == len(row["samples"]) and len(got["predicted"]) == got["total"]
    assert set(got["predicted"]) <= set(clf.classes["content"]) and "style_correct" not in got
    assert got["content_correct"] == sum(s["classified_as"] == "walk" for s in row["samples"])
    assert res["summary"]["classified"]["content_correct"] == got["content_correct"]
    assert res["summary"]["classified"]["share"] == pytest.approx(got["content_correct"] / got["total"], abs=1e-4)
    json.dumps(res)                                                     # results.json holds all of it
    # judged again from the stored measures alone, the table comes out the same
    again = rejudge(json.loads(json.dumps(res)))
    assert again["rows"] == res["rows"] and again["summary"] == res["summary"]
    report = report_markdown(res)
    assert "| walk | 12 (all) |" in report and "after the foot lock" in report
    assert f"{got['content_correct']}/{got['total']} |" in report and "in the prompt's action" in report


def test_reference_clips_follow_the_prompts_style_and_widen_only_when_too_few(tmp_path):
    from salad.data.labels import read_labels
    from salad.eval.fidelity import fidelity_classes, reference_clips

    root = write_tiny_dataset(tmp_path / "data", n=16)
    split = {n: f for f in ("train", "val", "test") for n in (root / f"{f}.txt").read_text().split()}
    names = sorted(split)
    styles = {n: ("normal" if i % 2 else "elderly") for i, n in enumerate(names)}
    for n in names[:4]:
        split[n] = "test"                                      # 2 normal and 2 elderly test clips
    (root / "labels.json").write_text(json.dumps(
        {n: {"content": "walk", "style": styles[n], "split": split[n]} for n in names}))
    labels = read_labels(root)
    walk = next(c for c in fidelity_classes(["walk"]))
    elderly = next(c for c in fidelity_classes(["walk/elderly"]))
    clips, used = reference_clips(root, walk, labels)
    normal_all = sum(1 for n in names if styles[n] == "normal")
    assert used == "all" and len(clips) == normal_all           # too few normal test clips: every split
    clips, used = reference_clips(root, elderly, labels)
    assert used == "all" and len(clips) == len(names) - normal_all
    for n in names[4:10]:
        split[n] = "test"
    (root / "labels.json").write_text(json.dumps(
        {n: {"content": "walk", "style": styles[n], "split": split[n]} for n in names}))
    clips, used = reference_clips(root, walk, read_labels(root))
    assert used == "test" and len(clips) == sum(1 for n in names if split[n] == "test" and styles[n] == "normal")
    # one unstyled take (and its mirror) in all: the class as captured, every style of every split, even
    # where the test split alone holds enough clips of a few other styles
    few = {n: ("normal" if n in names[:2] else styles[n] if styles[n] != "normal" else "proud") for n in names}
    (root / "labels.json").write_text(json.dumps(
        {n: {"content": "walk", "style": few[n], "split": split[n]} for n in names}))
    clips, used = reference_clips(root, walk, read_labels(root))
    assert used == "all, all styles" and len(clips) == len(names)


def test_a_fidelity_run_with_the_length_prior_generates_at_the_priors_length(tmp_path):
    root = _walks_labelled(tmp_path)
    pipe = load_pipeline()
    with pytest.raises(ValueError, match="'auto', 'model' or 'prior'"):
        evaluate_fidelity(pipe, root, length="longest")
    res = evaluate_fidelity(pipe, root, seeds=1, steps=2, sampler="dpm", classes=["walk"], length="prior")
    (row,) = res["rows"]
    assert sorted(s["frames"] for s in row["samples"]) == sorted(pipe.frames_for("prior", p) for p in HELD_OUT["walk"])
    assert res["settings"]["length"] == "prior" and "the length prior" in report_markdown(res)
    # the default holds the model's lengths within the prior's band, and the report says so
    res = evaluate_fidelity(pipe, root, seeds=1, steps=2, sampler="consistency", classes=["walk"])
    (row,) = res["rows"]
    bands = [pipe.auto_length_band(s["prompt"]) for s in row["samples"]]
    assert all(lo <= s["frames"] <= hi for s, (lo, hi) in zip(row["samples"], bands))
    assert res["settings"]["length_band"] > 1 and "held within" in report_markdown(res)
    # other seeds: the same prompts, each motion as a plain generation with that seed makes it
    res = evaluate_fidelity(pipe, root, seeds=2, steps=2, sampler="consistency", classes=["walk"], first_seed=5)
    (row,) = res["rows"]
    assert [s["seed"] for s in row["samples"]] == [5, 6] * len(HELD_OUT["walk"])
    again = pipe.generate(row["samples"][1]["prompt"], seed=6, steps=2, sampler="consistency", foot_lock=False)
    assert again.frames == row["samples"][1]["frames"]
    assert res["settings"]["first_seed"] == 5 and "2 seeds (5-6)" in report_markdown(res)
    with pytest.raises(ValueError, match="first_seed must be a non-negative integer"):
        evaluate_fidelity(pipe, root, seeds=1, first_seed=-1)


def _stored_bye_run(side: str) -> dict:
    """A stored run of one mirrored hand class, judged under an older rule (the real clips' majority)."""
    real = {"duration_s": 5.0, "root_speed_mps": 0.05, "hand_height_m": 0.8, "jerk_mps3": 8.0,
            "contact_slide_share": 0.1}
    refs = [{**real, "side": s} for s in ("left", "right", "left", "right")]
    samples = [{"prompt": "someone waves the right hand to part", "seed": i, "frames": 100,
                "raw": {**real, "side": side}, "clean": {**real, "side": side}} for i in range(3)]
    row = {"class": "bye", "reference": {"clips": 4, "splits": "test", "measures": refs}, "samples": samples,
           "raw": {"pass": False}, "clean": {"pass": False}}
    settings = {"seeds": 3, "steps": 50, "cfg": 7.5, "sampler": "ddim", "split": "test", "model": "m"}
    return {"rows": [row], "rules": {}, "settings": settings,
            "summary": {"raw": {"passed": 0, "classes": 1}, "clean": {"passed": 0, "classes": 1}}}


def test_a_stored_run_is_judged_again_from_its_measures(tmp_path, capsys):
    from salad.cli import main
    for side, passes in (("right", True), ("left", False)):
        src = tmp_path / side
        src.mkdir()
        (src / "results.json").write_text(json.dumps(_stored_bye_run(side)))
        assert main(["eval-fidelity", "--rejudge", str(src), "--out", str(tmp_path / f"{side}-out")]) == 0
        res = json.loads((tmp_path / f"{side}-out" / "results.json").read_text())
        assert res["rules"] == RULES and res["summary"]["raw"]["passed"] == int(passes)
        assert res["rows"][0]["raw"]["checks"]["side"]["real"] == "right"
        assert "## raw decoder output" in (tmp_path / f"{side}-out" / "report.md").read_text()
    # with --data the real clips are chosen and measured again: a run stored under the old rule, whose
    # reference was a few test clips of other styles, gets the class's every clip
    root = write_tiny_dataset(tmp_path / "data", n=8)
    names = [n for f in ("train", "val", "test") for n in (root / f"{f}.txt").read_text().split()]
    (root / "labels.json").write_text(json.dumps(
        {n: {"content": "bye", "style": "normal" if i < 2 else "happy", "split": "test" if i >= 4 else "train"}
         for i, n in enumerate(names)}))
    stored = _stored_bye_run("right")
    stored["rows"][0]["reference"]["splits"] = "test, all styles"
    before = json.dumps(stored, sort_keys=True)
    assert rejudge(stored, root)["rows"][0]["reference"]["splits"] == "all, all styles"
    assert json.dumps(stored, sort_keys=True) == before, "rejudging leaves the results it is given as they were"
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "results.json").write_text(json.dumps(stored))
    assert main(["eval-fidelity", "--rejudge", str(tmp_path / "old"), "--data", str(root)]) == 0
    ref = json.loads((tmp_path / "old" / "results.json").read_text())["rows"][0]["reference"]
    assert ref["splits"] == "all, all styles" and ref["clips"] == len(ref["measures"]) == len(names)
    assert max(m["duration_s"] for m in ref["measures"]) <= 196 / 20          # capped at the canvas
    assert main(["eval-fidelity", "--rejudge", str(tmp_path / "old"), "--data", str(tmp_path / "nothing")]) == 2
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "results.json").write_text("{}")
    assert main(["eval-fidelity", "--rejudge", str(tmp_path / "broken")]) == 2
    assert "not a readable eval-fidelity result" in capsys.readouterr().err
    assert main(["eval-fidelity", "--data", str(root), "--out", str(tmp_path / "x"), "--first-seed", "-2"]) == 2
    assert "--first-seed at least 0" in capsys.readouterr().err
    assert main(["eval-fidelity", "--out", str(tmp_path / "x")]) == 2           # nothing to judge, no data


def test_runs_with_other_seeds_pool_into_one_table_judged_on_every_seed(tmp_path, capsys):
    from salad.cli import main
    from salad.eval.fidelity import pool
    low, high = _stored_bye_run("right"), _stored_bye_run("right")
    for s in low["rows"][0]["samples"]:             # hands raised 0.2 m under the real median: a fail alone
        s["raw"] = {**s["raw"], "hand_height_m": 0.6}
    for i, s in enumerate(high["rows"][0]["samples"]):
        s["seed"] = 3 + i
    high["settings"]["first_seed"] = 3
    assert not rejudge(low)["rows"][0]["raw"]["checks"]["hand_height_m"]["pass"]
    before = json.dumps(low, sort_keys=True)
    pooled = rejudge(pool([low, high]))
    assert json.dumps(low, sort_keys=True) == before, "pooling leaves the runs as they were"
    assert len(pooled["rows"][0]["samples"]) == 6 and pooled["settings"]["seeds"] == 6
    check = pooled["rows"][0]["raw"]["checks"]["hand_height_m"]
    assert check["generated"] == pytest.approx(0.7) and check["pass"], "the median of all six motions"
    assert "6 seeds" in report_markdown(pooled)
    with pytest.raises(ValueError, match="share seeds"):
        pool([low, low])
    other = json.loads(json.dumps(high))
    other["settings"]["steps"] = 25
    with pytest.raises(ValueError, match="these differ: steps"):
        pool([low, other])
    for name, run in (("low", low), ("high", high)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(run))
    assert main(["eval-fidelity", "--rejudge", str(tmp_path / "low"), str(tmp_path / "high")]) == 2
    assert "needs --out" in capsys.readouterr().err
    assert main(["eval-fidelity", "--rejudge", str(tmp_path / "low"), str(tmp_path / "high"),
                 "--out", str(tmp_path / "both")]) == 0
    res = json.loads((tmp_path / "both" / "results.json").read_text())
    assert res["summary"]["raw"]["passed"] == 1 and res["settings"]["pooled_seeds"] == [0, 1, 2, 3, 4, 5]


def test_stored_runs_compare_side_by_side_with_the_checks_that_fail(tmp_path, capsys):
    from salad.cli import main
    runs = {"right": _stored_bye_run("right"), "left": _stored_bye_run("left")}
    runs["left"]["settings"]["prompt_set"] = "b"
    runs["left"]["rows"].append({**runs["left"]["rows"][0], "class": "byebye"})      # a class only one run has
    for name, run in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(run))
    out = tmp_path / "compare.md"
    assert main(["eval-fidelity", "--compare", str(tmp_path / "right"), f"{tmp_path / 'left'}:clean",
                 "--out", str(out)]) == 0
    table = out.read_text()
    assert table == capsys.readouterr().out
    head, _, bye, byebye, passed = table.splitlines()
    assert head == ("| class | set a, ddim 50, 3 seeds, raw | set b, ddim 50, 3 seeds, after the foot lock |")
    # judged under the current rules, as --rejudge would: the right hand is the one the prompt names
    assert bye == "| bye | ✓ | ✗ side 0.00 right |"
    assert byebye == "| byebye | – | ✗ side 0.00 right |"
    assert passed == "| classes passed | **1 / 1** | **0 / 2** |"
    assert main(["eval-fidelity", "--compare", str(tmp_path / "nowhere")]) == 2
    assert "not a readable eval-fidelity result" in capsys.readouterr().err
    assert main(["eval-fidelity", "--compare", str(tmp_path / "right"), "--rejudge", str(tmp_path / "right")]) == 2
