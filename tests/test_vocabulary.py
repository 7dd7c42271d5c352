import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from salad.eval.paraphrases import PROMPT_SETS
from salad.models.vocabulary import (ACTION_SIMILARITY, FEATURES_FILE, INDEX_DIMS, VOCABULARY_FILE, PromptCheck,
                                     build_vocabulary, save_vocabulary)

REPO = Path(__file__).resolve().parents[1]
EMBEDDED = REPO / "assets" / "model"

# Requests the Bandai captures hold nothing like (never used to set ACTION_SIMILARITY's neighbours'
# wording: each is checked for a warning of some kind, not for the action warning alone).
UNTRAINED = ["a person does a cartwheel", "a person jumps up and down", "a person sits down on a chair",
             "someone swims", "a man climbs a ladder", "a person throws a ball", "a person does push-ups",
             "a person kneels", "a person lies down on the floor", "a person crawls on hands and knees",
             "a person juggles", "a woman skips rope", "a person picks something up from the floor",
             "a person stretches their arms", "a person claps their hands", "a person spins around",
             "someone drinks from a cup", "a man does a backflip", "a person salutes"]
FOREIGN = ["une personne marche en avant", "eine Person geht vorwärts", "una persona camina hacia adelante",
           "le personnage court rapidement", "人が歩く"]


@pytest.fixture(scope="module")
def embedded_check():
    from salad.models.text import load_text_encoder

    check = PromptCheck.load(EMBEDDED, load_text_encoder("minilm"))
    assert check is not None, "the embedded model ships vocabulary.json (salad data vocabulary)"
    return check


def test_the_embedded_vocabulary_names_what_the_model_was_trained_on(embedded_check):
    v = embedded_check.vocab
    assert {"walk", "run", "kick", "bow", "wave-left-hand"} <= set(v.actions)
    assert v.actions["kick"] == "a person kicks" and "{" not in " ".join(v.actions.values())
    assert {"happily", "proudly", "wearily", "slowly", "briskly"} <= set(v.styles)
    assert embedded_check._features is not None, "the shipped features load without encoding anything"
    assert embedded_check.features.shape == (len(v.examples), 384)
    index = embedded_check.index
    assert index is not None and index.points.shape[1] == INDEX_DIMS and len(index.points) > 10 * len(v.examples)


def test_plain_trained_prompts_carry_no_warning(embedded_check):
    for prompt in ("a person walks forward", "a person waves their left hand", "someone runs forward happily",
                   "a man bows politely", "a person kicks"):
        assert embedded_check.warnings(prompt) == [], prompt


def test_untrained_actions_and_other_languages_are_flagged_with_the_nearest_known_motion(embedded_check):
    for prompt in UNTRAINED:
        warnings = embedded_check.warnings(prompt)
        assert warnings, prompt
    cartwheel = embedded_check.warnings("a person does a cartwheel")
    assert any("action the model was not trained on" in w and "closest known motion: 'a person" in w
               for w in cartwheel)
    assert any("'cartwheel'" in w for w in cartwheel)
    for prompt in FOREIGN:
        warnings = embedded_check.warnings(prompt)
        assert len(warnings) == 1 and "does not read as English" in warnings[0], (prompt, warnings)
        assert "closest known motion" in warnings[0]
    lazily = embedded_check.warnings("a person walks forward lazily")
    assert len(lazily) == 1 and "'lazily'" in lazily[0] and "happily" in lazily[0], "an unknown adverb lists known ones"


def test_a_side_given_to_a_part_no_caption_sides_is_flagged(embedded_check):
    # The Bandai captions side hands and arms only; a named leg derails the kick (README and assets/RESULTS.md, Limitations).
    assert embedded_check.sided_parts() == {"hand", "arm"}
    kick = embedded_check.warnings("a man kicks with his right leg")
    assert len(kick) == 1 and "no training caption names the right leg" in kick[0] and "arm, hand" in kick[0]
    assert embedded_check.unsided_parts("she stamps her left foot, then her right feet") == ["left foot", "right feet"]
    # sides the captions do name, in any number, and sides that name a direction, pass
    for prompt in ("a person walks forward and waves their right hand", "someone swings both arms",
                   "a person raises the left hands", "a person walks and turns right", "a person walks to the left"):
        assert embedded_check.unsided_parts(prompt) == [], prompt


def test_held_out_paraphrases_of_trained_actions_are_rarely_called_untrained(embedded_check):
    prompts = [p for held_out in PROMPT_SETS.values() for ps in held_out.values() for p in ps]
    flagged = [p for p in prompts if embedded_check.nearest(p, 1)[0][1] < ACTION_SIMILARITY]
    assert len(flagged) <= 3, flagged
    assert embedded_check.nearest("someone gives a polite bow", 1)[0][0] == "a person bows"


def test_generated_motions_carry_the_warnings(embedded_check):
    from salad.pipeline import load_pipeline

    pipe = load_pipeline()
    m = pipe.generate("a person does a cartwheel", seconds=1.0, steps=2)
    assert m.warnings == embedded_check.warnings("a person does a cartwheel") and m.warnings
    assert pipe.generate("a person walks forward", seconds=1.0, steps=2).warnings == []
    res = pipe.edit("a person walks forward", "a person swims forward", mode="swap", seconds=1.0, steps=2)
    assert res.source.warnings == [] and res.edited.warnings


def test_vocabulary_of_an_unlabelled_dataset_round_trips(tiny_dataset, tmp_path):
    from salad.models.text import load_text_encoder

    vocab = build_vocabulary(tiny_dataset)
    assert "a person walks forward" in vocab.actions and "walks" in vocab.words
    encoder = load_text_encoder("minilm")
    save_vocabulary(vocab, encoder, tmp_path)
    check = PromptCheck.load(tmp_path, encoder)
    assert check.vocab.to_json() == vocab.to_json() and check._features is not None
    assert check.nearest("a person walks forward", 1)[0] == ("a person walks forward", pytest.approx(1.0, abs=1e-2))
    assert check.warnings("a person walks forward") == []
    assert check.warnings("a person waves their left hand")          # no wave in the tiny walks
    # damaged or missing features are recomputed
    doc = json.loads((tmp_path / VOCABULARY_FILE).read_text())
    (tmp_path / FEATURES_FILE).write_bytes(b"not safetensors")
    damaged = PromptCheck.load(tmp_path, encoder)
    assert damaged._features is None and damaged.features.shape[0] == len(doc["examples"])
    torch.testing.assert_close(damaged.features, check.features, atol=2e-3, rtol=0)   # stored as fp16
    (tmp_path / FEATURES_FILE).unlink()
    assert PromptCheck.load(tmp_path, encoder).warnings("a person walks forward") == []
    (tmp_path / VOCABULARY_FILE).write_text("{broken")
    with pytest.raises(ValueError, match="unreadable vocabulary"):
        PromptCheck.load(tmp_path, encoder)
    assert PromptCheck.load(tmp_path / "nothing", encoder) is None


def test_cli_writes_the_vocabulary_and_generate_prints_warnings(tiny_model, tiny_dataset, tmp_path, cli):
    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    code, err = cli("data", "vocabulary", str(tiny_dataset), "--model", str(model))
    assert code == 0, err
    assert (model / VOCABULARY_FILE).is_file() and (model / FEATURES_FILE).is_file()
    assert "fitting the length net" in err, "a step of minutes on real data says what it is doing"
    code, err = cli("generate", "a person does a cartwheel", "-o", str(tmp_path / "c.npy"), "--model", str(model),
                    "--steps", "2", "--seconds", "1")
    assert code == 0, err
    assert "warning: 'a person does a cartwheel':" in err and "closest known motion" in err
    code, err = cli("generate", "a person walks forward", "-o", str(tmp_path / "w.npy"), "--model", str(model),
                    "--steps", "2", "--seconds", "1")
    assert code == 0 and "warning:" not in err
    code, err = cli("data", "vocabulary", str(tmp_path / "missing"), "--model", str(model))
    assert code == 2 and "salad: error:" in err
    # --index-only keeps the vocabulary (its sample, on which the warnings were set) and renews the index
    doc = json.loads((model / VOCABULARY_FILE).read_text())
    doc["examples"], doc["durations"], doc["speeds"] = doc["examples"][:1], doc["durations"][:1], doc["speeds"][:1]
    (model / VOCABULARY_FILE).write_text(json.dumps(doc))
    (model / FEATURES_FILE).unlink()
    code, err = cli("data", "vocabulary", str(tiny_dataset), "--model", str(model), "--index-only")
    assert code == 0, err
    assert json.loads((model / VOCABULARY_FILE).read_text())["examples"] == doc["examples"]
    from salad.models.text import load_text_encoder
    check = PromptCheck.load(model, load_text_encoder("minilm"))
    assert check._features.shape[0] == 1 and len(check.index.points) == len(build_vocabulary(tiny_dataset).captions)
    assert check.index.lengths is not None
    bare = tmp_path / "bare"
    shutil.copytree(tiny_model, bare)
    (bare / VOCABULARY_FILE).unlink(missing_ok=True)
    code, err = cli("data", "vocabulary", str(tiny_dataset), "--model", str(bare), "--index-only")
    assert code == 2 and "--index-only needs the model's vocabulary" in err


def test_the_vocabulary_keeps_each_examples_motion_length_for_a_length_prior(tiny_model, tiny_dataset, tmp_path):
    import numpy as np

    from salad.models.text import load_text_encoder
    from salad.pipeline import load_pipeline

    vocab = build_vocabulary(tiny_dataset)
    lengths = {}
    for name in (tiny_dataset / "train.txt").read_text().split():
        n = len(np.load(tiny_dataset / "new_joint_vecs" / f"{name}.npy")) / 20
        for line in (tiny_dataset / "texts" / f"{name}.txt").read_text().splitlines():
            lengths.setdefault(line.split("#")[0], []).append(n)
    assert len(vocab.durations) == len(vocab.examples)
    assert all(d == pytest.approx(np.median(lengths[c]), abs=0.01) for (_, c), d in zip(vocab.examples,
                                                                                       vocab.durations))
    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    save_vocabulary(vocab, load_text_encoder("minilm"), model)
    pipe = load_pipeline(model)
    for (_, caption), d in zip(vocab.examples, vocab.durations):       # a caption is its own nearest example
        assert pipe.prompt_check.nearest_seconds(caption, k=1) == pytest.approx(d)
    prior = pipe.prompt_check.length_prior("a person walks forward")
    # the length net's answer, which may stray a little past the lengths it was fitted to
    assert 0.8 * min(vocab.durations) <= prior <= 1.25 * max(vocab.durations)
    frames = pipe.frames_for("prior", "a person walks forward")
    assert frames == min(pipe.canvas_frames, int(round(prior * 20 / 4)) * 4)
    fixed = pipe.generate("a person walks forward", seconds="prior", seed=0, steps=2)
    assert fixed.frames == frames and fixed.info["length"] == "prior"
    own = pipe.generate("a person walks forward", seconds="model", seed=0, steps=2)
    assert own.info["length"] == "model" and own.frames % 4 == 0
    assert pipe.generate("a person walks forward", seconds=1.0, seed=0, steps=2).info["length"] == "requested"
    with pytest.raises(ValueError, match="'auto', 'model' or 'prior'"):
        pipe.frames_for("forever")
    # a vocabulary written before lengths were kept (and so before the caption index) still loads; it has no
    # prior to give
    doc = json.loads((model / VOCABULARY_FILE).read_text())
    del doc["durations"]
    (model / VOCABULARY_FILE).write_text(json.dumps(doc))
    (model / FEATURES_FILE).unlink()
    with pytest.raises(ValueError, match="keeps motion lengths"):
        load_pipeline(model).frames_for("prior", "a person walks forward")
    doc["durations"] = [1.0]
    (model / VOCABULARY_FILE).write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="durations"):
        load_pipeline(model)


def test_auto_length_is_the_models_own_held_within_the_priors_band(tiny_model, tiny_dataset, tmp_path,
                                                                    monkeypatch):
    import numpy as np

    import salad.pipeline as sp
    from salad.models.text import load_text_encoder
    from salad.pipeline import load_pipeline

    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    save_vocabulary(build_vocabulary(tiny_dataset), load_text_encoder("minilm"), model)
    pipe = load_pipeline(model)
    prompt = "a person walks forward"
    # the tiny data's motions outlast the tiny model's 2 s canvas; a prior inside it gives the band room
    assert pipe.auto_length_band(prompt) == (40, 40)
    monkeypatch.setattr(pipe.prompt_check, "length_prior", lambda prompt: 1.4)
    lo, hi = pipe.auto_length_band(prompt)
    assert (lo, hi) == (24, 36) and pipe.frames_for("prior", prompt) == 28
    steps = 10
    early = math.ceil(steps * sp.LENGTH_SETTLED) - 1       # steps reported before the watch stops one
    stopped_early = 0
    for seed in range(3):
        own = pipe.generate(prompt, seconds="model", seed=seed, steps=steps)
        ran = []
        auto = pipe.generate(prompt, seed=seed, steps=steps, progress=lambda i, n: ran.append((i, n)))
        # a sampling run again at a held length goes on counting: done 1, 2, ... of all the work so far
        assert [i for i, _ in ran] == list(range(1, len(ran) + 1)) and ran[-1][1] == len(ran)
        assert lo <= auto.frames <= hi
        if auto.info["length"] == "model":        # kept: the very same motion, sampled once
            assert lo <= own.frames <= hi and np.array_equal(auto.joints, own.joints) and len(ran) == steps
        else:                                     # sampled again at the band's edge, as a request of that length
            assert auto.info["length"] == "held" and auto.frames in (lo, hi)
            again = pipe.generate(prompt, seconds=auto.frames / 20, seed=seed, steps=steps)
            assert np.allclose(again.joints, auto.joints, atol=1e-5)
            # the first sampling stopped once its estimate had left the band, or ran on and ended outside it
            assert len(ran) == early + steps or (len(ran) == 2 * steps and not lo <= own.frames <= hi)
            stopped_early += len(ran) == early + steps
    # a band of one length holds every motion to the prior, in generate (each row of a batch) and in edits
    monkeypatch.setattr(sp, "AUTO_LENGTH_BAND", 1.0)
    frames = pipe.frames_for("prior", prompt)
    assert pipe.auto_length_band(prompt) == (frames, frames)
    assert [m.frames for m in pipe.generate(prompt, seed=0, steps=2, batch=2)] == [frames, frames]
    edit = pipe.edit(prompt, "a person runs forward", seed=0, steps=2)
    assert edit.source.frames == edit.edited.frames == frames and edit.source.info["length"] in ("held", "model")
    assert pipe.generate(prompt, seconds=1.0, seed=0, steps=2).frames == 20      # requested lengths stay
    # a length that has left a band of one frame count stops its sampling early, in generate and in edits
    for seed in range(3):
        ran = []
        pipe.generate(prompt, seed=seed, steps=steps, progress=lambda i, n: ran.append(i))
        stopped_early += len(ran) == early + steps
    ran = []
    edit = pipe.edit(prompt, "a person runs forward", seed=0, steps=steps, progress=lambda i, n: ran.append((i, n)))
    assert edit.source.frames == frames and len(ran) in (steps, early + steps, 2 * steps)
    assert [i for i, _ in ran] == list(range(1, len(ran) + 1)) and ran[-1][1] == len(ran)
    assert stopped_early > 0
    # the consistency sampler's few steps are not watched
    assert pipe._length_watch((frames, frames), 4, "consistency") is None and pipe._length_watch(None, 50, "ddim") is None


def test_the_length_prior_looks_among_every_training_caption_not_only_the_sample(tiny_dataset, tmp_path):
    import numpy as np
    from safetensors.torch import load_file, save_file

    from salad.models.text import load_text_encoder

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    names = (data / "train.txt").read_text().split()
    (data / "labels.json").write_text(json.dumps({n: {"content": "walk", "style": "normal", "dataset": 1,
                                                      "mirrored": False, "source": "synthetic", "split": "train"}
                                                  for n in names}))
    lengths, speeds = {}, {}
    for name in names:
        f = np.load(data / "new_joint_vecs" / f"{name}.npy")
        for line in (data / "texts" / f"{name}.txt").read_text().splitlines():
            lengths.setdefault(line.split("#")[0], []).append(len(f) / 20)
            speeds.setdefault(line.split("#")[0], []).append(np.linalg.norm(f[:, 1:3], axis=-1).mean() * 20)
    vocab = build_vocabulary(data, per_action=2)
    assert len(vocab.examples) == 2 < len(lengths)
    assert [c for c, _, _ in vocab.captions] == sorted(lengths)
    assert all(d == pytest.approx(np.median(lengths[c]), abs=0.01) and v == pytest.approx(np.median(speeds[c]), abs=1e-3)
               for c, d, v in vocab.captions)
    model = tmp_path / "model"
    encoder = load_text_encoder("minilm")
    save_vocabulary(vocab, encoder, model)
    assert "captions" not in json.loads((model / VOCABULARY_FILE).read_text()), "the index lives in the tensors"
    check = PromptCheck.load(model, encoder)
    assert check.index is not None and len(check.index.points) == len(vocab.captions)
    for caption, seconds, _ in vocab.captions:      # every caption, in the sample or not, is its own nearest
        assert check.nearest_seconds(caption, k=1) == pytest.approx(seconds, abs=0.01), caption
    # the length net fitted to those captions answers the prior, and reads their lengths back closely
    assert check.index.lengths is not None
    fitted = np.array([check.length_prior(c) / seconds for c, seconds, _ in vocab.captions])
    assert np.mean(np.abs(fitted - 1) <= 0.2) > 0.8, fitted
    without_net = {k: v for k, v in load_file(str(model / FEATURES_FILE)).items() if not k.startswith("length_net.")}
    save_file(without_net, str(model / FEATURES_FILE), metadata={"encoder": json.dumps(encoder.spec(), sort_keys=True)})
    before_net = PromptCheck.load(model, encoder)       # an index written before the net: the neighbours answer
    assert before_net.index is not None and before_net.index.lengths is None
    assert all(before_net.length_prior(c) == before_net.nearest_seconds(c) == check.nearest_seconds(c)
               for c, _, _ in vocab.captions[:5])
    sample = dict((c, d) for (_, c), d in zip(vocab.examples, vocab.durations))
    # an index made by another text encoder is left out, and so is a file without one: the examples answer
    tensors = load_file(str(model / FEATURES_FILE))
    save_file(tensors, str(model / FEATURES_FILE), metadata={"encoder": json.dumps({"name": "another"})})
    other = PromptCheck.load(model, encoder)
    assert other.index is None and other._features is None
    save_file({"pooled": tensors["pooled"]}, str(model / FEATURES_FILE),
              metadata={"encoder": json.dumps(encoder.spec(), sort_keys=True)})
    old = PromptCheck.load(model, encoder)
    assert old.index is None and old._features is not None
    for caption, d in sample.items():
        assert other.nearest_seconds(caption, k=1) == old.nearest_seconds(caption, k=1) == pytest.approx(d)
    tensors["index_seconds"][0] = -1.0                               # a damaged index is not used
    save_file(tensors, str(model / FEATURES_FILE), metadata={"encoder": json.dumps(encoder.spec(), sort_keys=True)})
    assert PromptCheck.load(model, encoder).index is None


def test_the_vocabulary_keeps_each_examples_root_speed_to_tell_actions_done_in_place(tiny_model, tiny_dataset,
                                                                                       tmp_path):
    import numpy as np

    from salad.models.text import load_text_encoder
    from salad.models.vocabulary import IN_PLACE_SPEED
    from salad.pipeline import load_pipeline

    vocab = build_vocabulary(tiny_dataset)
    speeds = {}
    for name in (tiny_dataset / "train.txt").read_text().split():
        f = np.load(tiny_dataset / "new_joint_vecs" / f"{name}.npy")
        joints_speed = np.linalg.norm(f[:, 1:3], axis=-1).mean() * 20
        for line in (tiny_dataset / "texts" / f"{name}.txt").read_text().splitlines():
            speeds.setdefault(line.split("#")[0], []).append(joints_speed)
    assert len(vocab.speeds) == len(vocab.examples)
    assert all(v == pytest.approx(np.median(speeds[c]), abs=1e-3) for (_, c), v in zip(vocab.examples, vocab.speeds))
    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    save_vocabulary(vocab, load_text_encoder("minilm"), model)
    check = load_pipeline(model).prompt_check
    for (_, caption), v in zip(vocab.examples, vocab.speeds):      # a caption is its own nearest example
        assert check.in_place(caption, k=1) == (v < IN_PLACE_SPEED)
    doc = json.loads((model / VOCABULARY_FILE).read_text())
    del doc["speeds"]
    (model / VOCABULARY_FILE).write_text(json.dumps(doc))
    (model / FEATURES_FILE).unlink()            # vocabularies without speeds had no caption index either
    assert load_pipeline(model).prompt_check.in_place("a person walks forward") is None
    doc["speeds"] = [-1.0] * len(doc["examples"])
    (model / VOCABULARY_FILE).write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="speeds"):
        load_pipeline(model)
