"""Where the pipeline runs: `device` in load_pipeline, Pipeline and the CLI, and an audit (tests/device_audit.py)
that runs every sampling path on the CPU while checking that nothing would break with the model on a GPU."""
import dataclasses

import numpy as np
import pytest
import torch

from device_audit import DeviceAudit
from salad.cli import main
from salad.editing.real import edit_real
from salad.eval.generators import VAEReconstruction
from salad.eval.sdedit import sdedit
from salad.models.vocabulary import PromptCheck
from salad.motion.real import load_real_motion
from salad.pipeline import EMBEDDED_MODEL, Pipeline, load_pipeline

no_gpu = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
PROMPT = "a person walks forward"


@torch.no_grad()
def test_the_audit_sees_what_a_gpu_would_refuse():
    lin = torch.nn.Linear(3, 2)
    device = torch.device("cpu")
    with DeviceAudit(device, [lin]) as audit:
        lin(torch.ones(4, 3).to(device)).cpu().numpy()                         # all where it belongs
        torch.randn(3, generator=torch.Generator().manual_seed(0)).to(lin.weight.device) + lin.bias[0]
        lin(torch.zeros(1, 3, device=lin.weight.device))[0, torch.tensor([1])]  # host index into the device
    assert audit.problems == []
    with DeviceAudit(device, [lin]) as audit:
        lin(torch.ones(4, 3))                                                  # host input, device weights
        lin(torch.ones(4, 3).to(device)).numpy()                               # device tensor read as NumPy
        torch.randn(3, generator=torch.Generator(), device=device)            # CPU generator onto the device
        torch.ones(2) + lin.bias                                               # a host tensor meets a device one
    assert [p.split(":")[0] for p in audit.problems] == ["linear", "numpy", "randn", "add"]


@pytest.fixture
def one_thread():
    # the audit's Python work between operations lets idle torch threads sleep; waking them on a busy
    # machine cost 10x the run time
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_every_sampling_path_keeps_its_tensors_on_the_pipeline_device(pipe, tiny_dataset, one_thread):
    """generate (both samplers, attention maps), generate_batch, edit, control (with and without an
    edit), real-motion editing with each inversion, SDEdit, the VAE reconstruction of `salad eval` and
    the prompt check, run with the model marked as being on the device."""
    name = (tiny_dataset / "test.txt").read_text().split()[0]
    real = load_real_motion(np.load(tiny_dataset / "new_joint_vecs" / f"{name}.npy"), pipe.canvas_frames, trim=True)
    targets = np.zeros((24, 22, 3), np.float32)
    targets[:, 0, 2] = np.linspace(0.0, 1.0, 24)
    mask = np.zeros((24, 22), bool)
    mask[::6, 0] = True
    check = PromptCheck.load(EMBEDDED_MODEL, pipe.text_encoder)
    assert check is not None and check._features is not None          # stored features, read on the CPU
    few = dataclasses.replace(check.vocab, examples=check.vocab.examples[:6])
    fresh = PromptCheck(few, pipe.text_encoder)                        # features made by the encoder
    with DeviceAudit(pipe.device, [pipe.denoiser, pipe.vae, pipe.text_encoder]) as audit:
        m = pipe.generate(PROMPT, seconds=1.2, seed=1, steps=4, return_attention=True)
        pipe.generate("someone turns left while walking", seed=2, steps=3, sampler="dpm")
        pipe.generate_batch([PROMPT, "a person jumps"], [16, 24], steps=3)
        pipe.edit(PROMPT, "a person runs forward", seconds=1.2, steps=4)
        pipe.edit(PROMPT, "a person walks forward slowly", mode="refine", mirror="upper", reweight={"slowly": 2.0},
                  seconds=1.2, steps=4)
        pipe.control(PROMPT, targets, mask, steps=4, refine_steps=3)
        pipe.control(PROMPT, targets, mask, steps=4, refine_steps=2, edit={"mode": "mirror", "mirror": "upper"})
        for inversion, extra in (("negative", {}), ("null_text", {"inner": 2}), ("fixed_point", {"iterations": 2})):
            edit_real(pipe, real.features, PROMPT, "a person runs forward", steps=3, inversion=inversion, **extra)
        sdedit(pipe, real, "a person runs forward", strength=0.5, steps=4)
        VAEReconstruction(pipe)([PROMPT], [real.frames], [real.features])
        check.warnings("a person moonwalks elegantly")
        fresh.warnings(PROMPT)
    assert audit.problems == [], "\n".join(dict.fromkeys(audit.problems))
    assert isinstance(m.attention.data, np.ndarray) and isinstance(m.joints, np.ndarray)


def test_cpu_asked_for_is_the_default_here(pipe, tiny_model):
    on_cpu = load_pipeline(tiny_model, device="cpu")
    on_cpu.set_projections(pipe.projections)         # as the shared pipeline, which decodes without projection
    on_cpu.set_foot_refine(pipe.foot_refine)         # and without feet refinement
    assert on_cpu.device == torch.device("cpu")
    assert all(p.device.type == "cpu" for m in (on_cpu.denoiser, on_cpu.vae, on_cpu.text_encoder)
               for p in m.parameters())
    if not torch.cuda.is_available():
        assert pipe.device == torch.device("cpu")                      # "auto" without a GPU
        a = pipe.generate(PROMPT, seconds=1.2, seed=5, steps=4)
        b = on_cpu.generate(PROMPT, seconds=1.2, seed=5, steps=4)
        # same device and same noise; only the reduction order may differ (other tests change torch's thread count)
        np.testing.assert_allclose(a.joints, b.joints, atol=1e-4)
        np.testing.assert_allclose(a.features, b.features, atol=1e-3)


@no_gpu
@pytest.mark.parametrize("device, match", [("cuda", "no CUDA GPU"), ("cuda:1", "no CUDA GPU"),
                                           ("meta", "not supported"), ("tpu", "unknown device")])
def test_a_device_that_is_not_there_is_refused_before_loading(tiny_model, monkeypatch, device, match):
    def loaded(*args, **kwargs):
        raise AssertionError("a model was loaded for a device that was refused")
    for name in ("load_vae", "load_denoiser", "load_text_encoder"):
        monkeypatch.setattr(f"salad.pipeline.{name}", loaded)
    with pytest.raises(ValueError, match=match):
        load_pipeline(tiny_model, device=device)


@no_gpu
def test_a_pipeline_refuses_a_device_before_moving_anything(pipe):
    parts = (pipe.vae, pipe.normalizer, pipe.latent_scale, pipe.denoiser, pipe.text_encoder, pipe.schedule,
             pipe.canvas_frames)
    for device, match in (("meta", "not supported"), ("cuda", "no CUDA GPU")):
        with pytest.raises(ValueError, match=match):
            Pipeline(*parts, device=device)
    assert next(pipe.denoiser.parameters()).device.type == "cpu"


def test_bf16_follows_the_pipeline_device(pipe, monkeypatch):
    asked = []
    monkeypatch.setattr("salad.pipeline.bf16_supported", lambda d: asked.append(d) or True)
    p = Pipeline(pipe.vae, pipe.normalizer, pipe.latent_scale, pipe.denoiser, pipe.text_encoder, pipe.schedule,
                 pipe.canvas_frames, bf16=True, device="cpu")
    assert asked == [p.device] and p.bf16
    ctx = p.autocast()
    assert isinstance(ctx, torch.autocast) and ctx.device == p.device.type and ctx.fast_dtype == torch.bfloat16


def test_bf16_from_a_number_of_rows(pipe, monkeypatch):
    """bf16_min_rows = 2 (the default, and the studio's auto precision): a guided step's paired rows run in
    bf16, a single row (the conditional rows alone, below the guidance cutoff) in fp32; the reports and the
    replay key say so."""
    monkeypatch.setattr("salad.pipeline.bf16_supported", lambda d: True)
    parts = (pipe.vae, pipe.normalizer, pipe.latent_scale, pipe.denoiser, pipe.text_encoder, pipe.schedule,
             pipe.canvas_frames)
    p = Pipeline(*parts, bf16=True, device="cpu")
    seen, net = [], p.denoiser
    monkeypatch.setattr(p, "_network_call", lambda name: lambda x, *a, **kw: (
        seen.append((x.shape[0], torch.is_autocast_enabled("cpu"))) or net(x, *a, **kw)))
    fn = p.model_fn(p.sampler_text(["a person walks"], "ddim"), auto=False)
    x, t = torch.randn(2, 4, 7, net.config.latent_dim), torch.full((2,), 500)
    assert fn(x, t).dtype == torch.float32
    fn.conditional(x[1:], t[1:])
    assert seen == [(2, True), (1, False)]
    assert p.precision == "bf16 autocast from 2 rows a forward"
    assert p.sampler_settings("ddim")["precision"] == p.precision
    every = Pipeline(*parts, bf16=True, bf16_min_rows=1, device="cpu")
    assert every.precision == "bf16 autocast"
    key = ("a person walks", None, 0, 10, 7.5, "ddim")
    assert p.source_key(*key) != every.source_key(*key), "a run recorded in one precision is not replayed in another"
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="bf16_min_rows"):
            Pipeline(*parts, bf16=True, bf16_min_rows=bad, device="cpu")


@no_gpu
@pytest.mark.parametrize("argv", [
    ["generate", PROMPT, "-o", "{tmp}/w.npy"],
    ["edit", PROMPT, "--mode", "mirror", "--mirror", "upper", "-o", "{tmp}/e"],
    ["control", PROMPT, "--path-preset", "line", "-o", "{tmp}/c.npy"],
    ["edit-real", "{tmp}/in.bvh", "--source", PROMPT, "--mode", "mirror", "--mirror", "all", "-o", "{tmp}/r.bvh"],
    ["eval", "--data", "{tmp}/data", "--out", "{tmp}/out"],
    ["eval-length", "--data", "{tmp}/data", "--out", "{tmp}/out"],
    ["eval-real-edit", "--data", "{tmp}/data", "--out", "{tmp}/out"],
])
def test_cli_device_is_checked_first(argv, tmp_path, capsys):
    args = [a.format(tmp=tmp_path) for a in argv] + ["--model", str(tmp_path / "nowhere"), "--device", "cuda"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "no CUDA GPU" in err and "--device cpu" in err, err


@no_gpu
def test_eval_vae_checks_the_device_first(tmp_path, capsys):
    assert main(["eval-vae", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out"),
                 "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "no CUDA GPU" in err and "--device cpu" in err, err
