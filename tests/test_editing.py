import numpy as np
import pytest
import torch

from salad.editing.align import align_tokens, align_words
from salad.editing.controllers import (AttentionEdit, HoldParts, KeepSource, Mirror, Refine, Reweight, WordSwap,
                                       cfg_rows)
from salad.editing.store import AttentionStore, to_motion_rate
from salad.models.attention import AttentionCall
from salad.models.text import load_text_encoder


@pytest.fixture(scope="module")
def encoder():
    return load_text_encoder("minilm")


def maps(b=1, h=2, T=3, J=7, L=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, h, T, J, L, generator=g).softmax(-1)


def test_refine_alignment_survives_insertions_in_the_middle(encoder):
    src, tgt = "a person walks forward", "a person walks slowly forward while waving"
    assert align_words(src.split(), tgt.split(), "refine") == [0, 1, 2, -1, 3, -1, -1]
    text = encoder.encode(["", "", src, tgt])
    al = align_tokens(text, 2, 3, "refine")
    s_tok = {w: text.token_indices(2, i) for i, w in enumerate(text.words[2])}
    t_tok = {w: text.token_indices(3, i) for i, w in enumerate(text.words[3])}
    # "forward" sits at a later position in the target, and still reads the source's "forward" column
    for a, b in zip(s_tok["forward"], t_tok["forward"]):
        assert al.weights[a, b] == 1.0 and b > a
    for w in ("slowly", "while", "waving"):
        assert all(al.inserted[k] for k in t_tok[w])
    assert not any(al.inserted[k] for k in t_tok["forward"] + t_tok["person"])
    # the end token maps to the end token despite the shift
    s_end = int(text.mask[2].sum()) - 1
    t_end = int(text.mask[3].sum()) - 1
    assert al.weights[s_end, t_end] == 1.0


def test_swap_pairs_words_by_position_and_needs_equal_length(encoder):
    text = encoder.encode(["", "", "a person walks forward", "a person runs forward"])
    al = align_tokens(text, 2, 3, "swap")
    assert al.word_map == [0, 1, 2, 3]
    src = torch.zeros(1, text.tokens.shape[1])
    src[0, text.token_indices(2, 2)] = 1.0             # all attention on "walks"
    out = al.apply(src)
    assert out[0, text.token_indices(3, 2)].sum() == pytest.approx(1.0)   # lands on "runs"
    with pytest.raises(ValueError, match="same number of words"):
        align_words(["a", "b"], ["a", "b", "c"], "swap")


def test_a_swap_led_by_the_source_for_one_step_lets_the_new_word_keep_its_map(encoder):
    from salad.editing.build import build_edit
    from salad.editing.spec import EditSpec

    text = encoder.encode(["a person walks and turns right", "a person walks and turns left"])
    spec = EditSpec(mode="swap", target="a person walks and turns left")

    def rule(steps, tau=None):
        s = spec if tau is None else EditSpec(mode="swap", target=spec.target, tau=tau)
        return build_edit(text, steps, 40, s, "a person walks and turns right", spec.target,
                          cfg_layout=False).controller.rule
    # the consistency student's 4 steps at tau 0.8: the source leads the first step only
    assert rule(4).own_replaced and rule(5).own_replaced
    # DDIM's 50: ten steps, the source's maps for every word (Prompt-to-Prompt's swap)
    assert not rule(50).own_replaced and not rule(6).own_replaced
    assert rule(50, tau=0.99).own_replaced and not rule(4, tau=0.5).own_replaced


def test_rule_semantics_on_small_tensors(encoder):
    text = encoder.encode(["", "", "a person walks", "a person runs"])
    L = text.tokens.shape[1]
    al = align_tokens(text, 2, 3, "swap")
    src, tgt = maps(L=L, seed=1), maps(L=L, seed=2)
    # tau = 1: the switch happens at the start, the target's own maps throughout
    for progress in (0.0, 0.5, 0.99):
        assert torch.equal(WordSwap(al, tau=1.0)(src, tgt, progress), tgt)
    # tau = 0: the switch never happens, the (aligned) source maps throughout
    for progress in (0.0, 0.5, 0.99):
        assert torch.equal(WordSwap(al, tau=0.0)(src, tgt, progress), al.apply(src))
    # default tau = 0.8T: source for the first 20% of the steps
    sw = WordSwap(al)
    assert torch.equal(sw(src, tgt, 0.1), al.apply(src)) and torch.equal(sw(src, tgt, 0.3), tgt)
    # own_replaced: in the source-led steps the swapped word ("runs") keeps its own map, the others the source's
    swapped = text.token_indices(3, 2)
    assert al.replaced.nonzero().flatten().tolist() == swapped
    own = WordSwap(al, own_replaced=True)(src, tgt, 0.1)
    assert torch.equal(own[..., swapped], tgt[..., swapped])
    kept = [k for k in range(L) if k not in swapped]
    assert torch.equal(own[..., kept], al.apply(src)[..., kept])
    assert torch.equal(WordSwap(al, own_replaced=True)(src, tgt, 0.3), tgt)
    assert torch.equal(KeepSource()(src, tgt, 0.5), src)

    ref_text = encoder.encode(["", "", "a person walks", "a person walks happily"])
    ral = align_tokens(ref_text, 2, 3, "refine")
    assert not ral.replaced.any()                      # refine adds words; it replaces none
    L = ref_text.tokens.shape[1]
    src, tgt = maps(L=L, seed=3), maps(L=L, seed=4)
    out = Refine(ral)(src, tgt, 0.5)
    new = ref_text.token_indices(3, 3)                 # "happily"
    assert torch.equal(out[..., new], tgt[..., new])
    kept = ref_text.token_indices(3, 2)                # "walks"
    assert torch.equal(out[..., kept], src[..., ref_text.token_indices(2, 2)])


def test_transforms_mirror_and_reweight():
    m = maps()
    for part in ("lower", "upper", "all"):
        mir = Mirror(part)
        assert torch.equal(mir(mir(m)), m)
        assert not torch.equal(mir(m), m)
    before = m.clone()
    up = Mirror("upper")(m)
    assert torch.equal(m, before), "mirroring never changes the maps it reads"
    assert torch.equal(up[:, :, :, 4], m[:, :, :, 5]) and torch.equal(up[:, :, :, 1], m[:, :, :, 1])
    assert torch.equal(Reweight([2, 3], 1.0)(m), m)
    r = Reweight([2], -2.0)(m)
    assert torch.allclose(r[..., 2], -2.0 * m[..., 2]) and torch.equal(r[..., 0], m[..., 0])
    with pytest.raises(ValueError):
        Reweight([2], 3.5)
    with pytest.raises(ValueError):
        Mirror("arms")


def test_attention_edit_touches_only_the_conditional_target_rows():
    rows = cfg_rows(1)                                  # [src_u, tgt_u, src_c, tgt_c]
    edit = AttentionEdit(rows, steps=10, rule=KeepSource(), transforms=[Mirror("all")], self_inject=0.2)
    T, J, L, H = 3, 7, 5, 2
    temporal = torch.rand(4 * J, H, T, T).softmax(-1)
    cross = torch.rand(4, H, T * J, L).softmax(-1)
    t_out = edit(AttentionCall("temporal", 0, temporal, 4, T, J))
    perm = Mirror("all").perm
    # the injected source self-attention is mirrored too: target part p takes source part perm[p]
    assert torch.equal(t_out[3 * J:], temporal[2 * J:3 * J][perm]) and torch.equal(t_out[:3 * J], temporal[:3 * J])
    skeletal = torch.rand(4 * T, H, J, J).softmax(-1)
    s_out = edit(AttentionCall("skeletal", 0, skeletal, 4, T, J))
    assert torch.equal(s_out[3 * T:], skeletal[2 * T:3 * T][:, :, perm][:, :, :, perm])
    c_out = edit(AttentionCall("cross", 0, cross, 4, T, J))
    grid_in, grid_out = cross.view(4, H, T, J, L), c_out.view(4, H, T, J, L)
    assert torch.equal(grid_out[:3], grid_in[:3])
    assert torch.equal(grid_out[3], Mirror("all")(grid_in[2:3])[0])
    # after the injection window, self-attention is left alone
    for _ in range(2):
        edit(AttentionCall("temporal", 0, temporal, 4, T, J))
    late = edit(AttentionCall("temporal", 0, temporal, 4, T, J))
    assert torch.equal(late, temporal)


def test_attention_store_memory_is_bounded(encoder):
    text = encoder.encode(["", "a person waves their left hand"])
    T, J, L = 10, 7, text.tokens.shape[1]
    sizes = []
    for heads in (2, 8):
        store = AttentionStore(text, rows=slice(1, 2), frames=4 * T, steps=(0, 3))
        for step in range(6):
            for layer in range(5):
                store(AttentionCall("cross", layer, torch.rand(2, heads, T * J, L).softmax(-1), 2, T, J))
        sizes.append(store.nbytes())
        maps_ = store.maps(0)
    assert sizes[0] == sizes[1] == 3 * 5 * T * J * L * 2, "3 steps x 5 layers, head-averaged, fp16"
    assert maps_.aggregate().shape == (6, 7, 4 * T)
    assert maps_.words == ["a", "person", "waves", "their", "left", "hand"]


def test_latent_to_motion_rate():
    m = np.arange(4, dtype=float)[None]
    out = to_motion_rate(m, 16)
    assert out.shape == (1, 16) and out[0, 0] == 0 and out[0, -1] == 3
    assert np.all(np.diff(out[0]) >= 0)


MODES = [
    dict(mode="swap", target_prompt="a person runs forward"),
    dict(mode="refine", target_prompt="a person walks forward while waving"),
    dict(mode="reweight", reweight={"walks": 2.0}),
    dict(mode="mirror", mirror="upper"),
    dict(mode="refine", target_prompt="a person walks forward happily", reweight={"happily": 2.5}),
]


@pytest.mark.parametrize("kw", MODES, ids=lambda kw: kw["mode"] + ("+reweight" if "reweight" in kw and kw["mode"] != "reweight" else ""))
def test_end_to_end_edits_with_a_trained_model(tiny_model, kw):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)   # its L-BFGS through the tiny VAE magnifies the last digits batched and single rows differ in
    res = pipe.edit("a person walks forward", seed=1, seconds=1.6, steps=6, **kw)
    assert res.source.joints.shape == res.edited.joints.shape == (32, 22, 3)
    assert np.isfinite(res.edited.joints).all()
    plain = pipe.generate("a person walks forward", seconds=1.6, seed=1, steps=6)
    np.testing.assert_allclose(res.source.joints, plain.joints, atol=5e-3)  # the source branch is untouched
    assert res.edited_attention.aggregate().shape[1:] == (7, 32)
    assert not np.allclose(res.source.joints, res.edited.joints)


def test_held_parts_take_the_source_rows_latents():
    x = torch.randn(2, 5, 7, 4)
    out = HoldParts("lower")(x)
    assert torch.equal(out[1, :, :3], x[0, :, :3]) and torch.equal(out[1, :, 3:], x[1, :, 3:])
    assert torch.equal(out[0], x[0]) and not torch.equal(out, x)
    up = HoldParts("upper")(x)
    assert torch.equal(up[1, :, 3:], x[0, :, 3:]) and torch.equal(up[1, :, :3], x[1, :, :3])
    with pytest.raises(ValueError, match="held parts"):
        HoldParts("legs")


@pytest.mark.parametrize("hold", ["lower", "upper", None])
def test_edit_holds_the_asked_parts_of_the_source_latents(tiny_model, hold):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)   # its L-BFGS through the tiny VAE magnifies the last digits batched and single rows differ in
    seen = {}
    decode = pipe.decode

    def keep_latents(z, *a, **kw):
        seen["z"] = z.clone()
        return decode(z, *a, **kw)
    pipe.decode = keep_latents
    res = pipe.edit("a person walks forward", mode="reweight", reweight={"walks": -2.0}, hold=hold, seed=1,
                    seconds=1.6, steps=6)
    z = seen["z"]
    held = {"lower": [0, 1, 2], "upper": [3, 4, 5, 6], None: []}[hold]
    free = [p for p in range(7) if p not in held]
    assert torch.equal(z[1, :, held], z[0, :, held])
    assert not torch.allclose(z[1, :, free], z[0, :, free])
    assert res.params["hold"] == hold
    plain = pipe.generate("a person walks forward", seconds=1.6, seed=1, steps=6)
    np.testing.assert_allclose(res.source.joints, plain.joints, atol=5e-3)  # the source branch is untouched


def test_holding_parts_is_refused_where_latents_are_not_blended(tiny_model):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    targets = np.zeros((32, 22, 3), dtype=np.float32)
    mask = np.zeros((32, 22), dtype=bool)
    mask[-1, 0] = True
    with pytest.raises(ValueError, match="guided control does not hold parts"):
        pipe.control("a person walks forward", targets=targets, mask=mask, steps=2,
                     edit={"mode": "reweight", "reweight": {"walks": 2.0}, "hold": "lower"})
    # "auto" holds nothing there, and says so
    res = pipe.control("a person walks forward", targets=targets, mask=mask, steps=2,
                       edit={"mode": "reweight", "reweight": {"walks": 2.0}})
    assert res.params["hold"] is None


def test_swap_with_tau_at_the_start_is_target_only_generation(tiny_model):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)   # its L-BFGS through the tiny VAE magnifies the last digits batched and single rows differ in
    res = pipe.edit("a person walks forward", "a person runs forward", mode="swap", tau=1.0, self_inject=0.0,
                    seed=2, seconds=1.2, steps=5)
    target_only = pipe.generate("a person runs forward", seconds=1.2, seed=2, steps=5)
    np.testing.assert_allclose(res.edited.joints, target_only.joints, atol=5e-3)


# edits that move the tiny model's motion by millimetres at least (its upper-body mirror moves it 0.03 mm)
REPLAYED = [kw for kw in MODES if kw["mode"] != "mirror"] + [
    dict(mode="mirror", mirror="all"), dict(mode="reweight", reweight={"walks": -2.0}, hold="lower")]


@pytest.mark.parametrize("kw", REPLAYED, ids=lambda kw: kw["mode"] + ("+hold" if "hold" in kw else ""))
def test_an_edit_of_a_recorded_source_runs_the_edited_branch_alone_to_the_same_motion(tiny_model, kw):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model, bf16=False)
    pipe.set_foot_refine(0)
    args = dict(seed=1, seconds=1.6, steps=6)
    rows = []
    forward = pipe.denoiser.forward
    pipe.denoiser.forward = lambda z, *a, **k: rows.append(z.shape[0]) or forward(z, *a, **k)
    first = pipe.edit("a person walks forward", **args, **kw)     # four rows, the source branch recorded
    seen, rows[:] = list(rows), []
    again = pipe.edit("a person walks forward", **args, **kw)     # two rows, the source's maps and latents read back
    assert set(seen) <= {4, 2} and max(seen) == 4 and max(rows) == 2   # (unguided steps drop the unconditional rows)
    assert not first.edited.info["source_replayed"] and again.edited.info["source_replayed"]
    np.testing.assert_allclose(again.source.joints, first.source.joints, atol=1e-4)
    moved = np.abs(first.edited.joints - first.source.joints).max()
    gap = np.abs(again.edited.joints - first.edited.joints).max()
    assert gap < min(1e-4, moved / 5), (gap, moved)     # the same edit, not the source sampled again
    np.testing.assert_allclose(again.edited_attention.data, first.edited_attention.data, atol=5e-3)
    np.testing.assert_array_equal(again.source_attention.data, first.source_attention.data)
    assert again.params == first.params


def test_a_replayed_edit_runs_self_attention_fused_once_the_injection_is_over(tiny_model, monkeypatch):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model, bf16=False)
    pipe.set_foot_refine(0)
    args = dict(seed=1, seconds=1.6, steps=10, mode="mirror", mirror="all", self_inject=0.3)
    seen = []
    edit_call = AttentionEdit.__call__
    monkeypatch.setattr(AttentionEdit, "__call__",
                        lambda self, call: seen.append((call.kind, self.counter.step)) or edit_call(self, call))
    pipe.edit("a person walks forward", **args)                 # sampled: every map drawn, for the recording
    assert {s for k, s in seen if k != "cross"} == set(range(10))
    seen.clear()
    again = pipe.edit("a person walks forward", **args)         # replayed: self-attention maps for 3 steps only
    assert again.edited.info["source_replayed"]
    assert {s for k, s in seen if k != "cross"} == {0, 1, 2} and {s for k, s in seen if k == "cross"} == set(range(10))


def test_an_edit_replays_the_generated_motion_it_starts_from_and_nothing_else(tiny_model):
    from salad.editing.replay import SourceRun
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model, bf16=False)
    pipe.set_foot_refine(0)
    prompt, args = "a person walks forward", dict(seed=3, seconds=1.6, steps=6)
    shown = pipe.generate(prompt, **args, return_attention=True)
    res = pipe.edit(prompt, "a person runs forward", **args)
    assert res.edited.info["source_replayed"]
    np.testing.assert_allclose(res.source.joints, shown.joints, atol=1e-4)
    pipe.source_runs.clear()
    fresh = pipe.edit(prompt, "a person runs forward", **args)
    assert not fresh.edited.info["source_replayed"]
    np.testing.assert_allclose(res.edited.joints, fresh.edited.joints, atol=1e-3)
    # another seed or sampler setting is another source: sampled, not replayed
    assert not pipe.edit(prompt, "a person runs forward", **dict(args, seed=4)).edited.info["source_replayed"]
    pipe.set_sampling(cfg_rescale=0.0)
    assert not pipe.edit(prompt, "a person runs forward", **args).edited.info["source_replayed"]
    # a generate that returns no maps records nothing (it may run fused attention, or compiled)
    pipe.source_runs.clear()
    pipe.generate(prompt, **args)
    assert len(pipe.source_runs) == 0
    # recorded beside a longer target prompt (its maps padded to that batch's tokens), replayed beside a shorter one
    pipe.edit(prompt, "a person walks forward happily and slowly", mode="refine", **args)
    mirrored = pipe.edit(prompt, mode="mirror", mirror="all", **args)
    assert mirrored.edited.info["source_replayed"]
    pipe.source_runs.clear()
    np.testing.assert_allclose(mirrored.edited.joints,
                               pipe.edit(prompt, mode="mirror", mirror="all", **args).edited.joints, atol=1e-4)
    # a source whose automatic length left its band is sampled at the band's edge straight away
    pipe.auto_length_band = lambda text: (32, 64)      # (the tiny model ships no length prior)
    pipe.source_runs.put(pipe.source_key(prompt, None, 5, 6, 7.5, "ddim"), SourceRun(held_frames=40, band=(32, 64)))
    held = pipe.edit(prompt, "a person runs forward", seed=5, steps=6)
    assert held.source.frames == held.edited.frames == 40 and held.edited.info["length"] == "held"
    # the model's own length holds to no band: the same sampling runs whole
    free = pipe.edit(prompt, "a person runs forward", seed=5, steps=6, seconds="model")
    assert free.edited.info["length"] == "model" and not free.edited.info["source_replayed"]


def test_recorded_source_runs_are_bounded():
    from salad.editing.replay import SourceRun, SourceRuns
    runs = SourceRuns(2)
    for k in "abc":
        runs.put(k, SourceRun(held_frames=40))
    assert len(runs) == 2 and runs.get("a") is None and runs.get("c") is not None
    runs.get("b")
    runs.put("d", SourceRun())
    assert runs.get("b") is not None and runs.get("c") is None      # least recently used goes first
    none = SourceRuns(0)
    none.put("a", SourceRun())
    assert len(none) == 0
    with pytest.raises(ValueError, match="capacity"):
        SourceRuns(-1)


def test_edit_input_errors(tiny_model):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    with pytest.raises(ValueError, match="mode"):
        pipe.edit("a person walks", mode="paint")
    with pytest.raises(ValueError, match="target prompt"):
        pipe.edit("a person walks", mode="swap")
    with pytest.raises(ValueError, match="same number of words"):
        pipe.edit("a person walks", "a person walks fast", mode="swap", steps=2)
    with pytest.raises(ValueError, match="not a word"):
        pipe.edit("a person walks", mode="reweight", reweight={"jumps": 2.0}, steps=2)


def test_cli_edit_writes_npy_bvh_and_side_by_side(tiny_model, tmp_path):
    import subprocess
    import sys
    from pathlib import Path
    import imageio.v3 as iio
    repo = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-m", "salad.cli", "edit", "a person waves their left hand", "--mode", "mirror",
                          "--mirror", "upper", "--model", str(tiny_model), "--seconds", "1.2", "--steps", "3",
                          "-o", str(tmp_path / "e")], cwd=repo, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    for f in ("source.npy", "edited.npy", "source.bvh", "edited.bvh", "side_by_side.mp4"):
        assert (tmp_path / "e" / f).stat().st_size > 0
    frames = iio.imread(tmp_path / "e" / "side_by_side.mp4", plugin="FFMPEG")
    assert frames.shape[0] == 24 and frames.shape[2] > frames.shape[1]


def test_cli_edit_holds_the_chosen_parts_and_refuses_others(tiny_model, tmp_path, capsys):
    from salad.cli import build_parser, main
    argv = ["edit", "a person waves their left hand", "--mode", "reweight", "--reweight", "waves=2",
            "--model", str(tiny_model), "--seconds", "1.2", "--steps", "2", "-o", str(tmp_path / "e")]
    assert main(argv + ["--hold", "lower"]) == 0
    assert "held the lower body to the source" in capsys.readouterr().out
    assert (tmp_path / "e" / "edited.npy").stat().st_size > 0
    parser = build_parser()
    assert parser.parse_args(argv).hold == "auto" and parser.parse_args(argv + ["--hold", "none"]).hold == "none"
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(argv + ["--hold", "legs"])
    assert exit_.value.code == 2 and "invalid choice: 'legs'" in capsys.readouterr().err
    # real-motion editing holds no parts: edit-real has no --hold
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(["edit-real", "in.bvh", "--source", "a person walks", "-o", "a.bvh", "--hold", "lower"])
    assert exit_.value.code == 2 and "unrecognized arguments: --hold lower" in capsys.readouterr().err
