import json

import pytest
import torch

from salad.models.denoiser import Denoiser, DenoiserConfig
from salad.models.widen import widen, widened_config


def trained_looking(**kw) -> Denoiser:
    torch.manual_seed(0)
    model = Denoiser(DenoiserConfig(dim=32, heads=2, ff_dim=64, layers=3, latent_dim=8, text_dim=16, **kw))
    with torch.no_grad():       # zero-initialised parts (the guidance MLP's output) must matter too
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


@pytest.mark.parametrize("student", [False, True])
def test_the_widened_denoiser_computes_what_the_narrow_one_did(student):
    narrow = trained_looking(guidance_embedding=student).eval()
    wide = widen(narrow)
    c = wide.config
    assert (c.dim, c.heads, c.ff_dim, c.sinusoid_dim) == (64, 4, 128, 32) and c == widened_config(narrow.config)
    assert not wide.training
    assert sum(p.numel() for p in wide.parameters()) > 3.5 * sum(p.numel() for p in narrow.parameters())

    g = torch.Generator().manual_seed(1)
    z, text = torch.randn(3, 10, 7, 8, generator=g), torch.randn(3, 6, 16, generator=g)
    text_mask, frame_mask = torch.ones(3, 6, dtype=torch.bool), torch.ones(3, 10, dtype=torch.bool)
    text_mask[0, 4:], frame_mask[1, 7:] = False, False
    kw = dict(text_mask=text_mask, frame_mask=frame_mask, auto_length=torch.tensor([True, False, True]))
    if student:
        kw["guidance"] = torch.tensor([1.0, 3.0, 7.5])
    t = torch.tensor([3, 500, 999])
    with torch.no_grad():
        before, after = narrow(z, t, text, **kw), wide(z, t, text, **kw)
    assert before.abs().mean() > 0.05
    torch.testing.assert_close(after, before, atol=2e-5, rtol=1e-4)
    # and it is a model of its own: a change to one copy of a channel changes the output
    with torch.no_grad():
        wide.layers[1].ff[0].weight[70] += 1.0
        assert not torch.allclose(wide(z, t, text, **kw), before, atol=1e-3)


def test_dropout_gives_the_two_copies_different_gradients():
    wide = widen(trained_looking(dropout=0.1)).train()
    g = torch.Generator().manual_seed(2)
    z, text = torch.randn(2, 6, 7, 8, generator=g), torch.randn(2, 4, 16, generator=g)
    wide(z, torch.tensor([100, 800]), text).pow(2).mean().backward()
    grad = wide.layers[0].temporal.to_q.weight.grad            # rows 0-31: the old channels, 32-63: their copies
    assert grad[:32].abs().sum() > 0
    assert not torch.allclose(grad[:32], grad[32:], atol=1e-6)


def test_training_from_a_narrow_checkpoint_widens_it_and_keeps_its_loss(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main
    from tests.conftest import denoiser_toml

    def val_loss(cfg):
        assert main(["train", "denoiser", "--config", str(cfg), "--vae", str(tiny_model / "vae"),
                     "--init-from", str(tiny_model / "denoiser"), "--validate-only"]) == 0
        return json.loads(capsys.readouterr().out.strip().splitlines()[-1])["val_loss"]

    narrow = denoiser_toml(tmp_path / "narrow.toml", tiny_dataset, steps=2)
    wide = tmp_path / "wide.toml"
    wide.write_text(narrow.read_text().replace("dim = 32\nheads = 4\nff_dim = 64",
                                               "dim = 64\nheads = 8\nff_dim = 128\nsinusoid_dim = 32"))
    assert "sinusoid_dim = 32" in wide.read_text()
    assert val_loss(wide) == pytest.approx(val_loss(narrow), abs=1e-4)
    # twice as wide, but with sinusoids of its own width, it is a different function: refused, not loaded
    other = tmp_path / "other.toml"
    other.write_text(wide.read_text().replace("sinusoid_dim = 32\n", ""))
    assert main(["train", "denoiser", "--config", str(other), "--vae", str(tiny_model / "vae"),
                 "--init-from", str(tiny_model / "denoiser"), "--validate-only"]) == 2
    assert "weights do not fit the model" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [-32, 24, 33])
def test_sinusoid_widths_that_cannot_tile_the_model_are_refused(bad):
    with pytest.raises(ValueError, match="sinusoid_dim"):
        Denoiser(DenoiserConfig(dim=64, heads=2, ff_dim=64, layers=1, sinusoid_dim=bad))
