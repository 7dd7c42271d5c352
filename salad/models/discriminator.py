"""A slicing adversarial network (SAN) discriminator over motion features (MoLA §3.2, App. A).

The discriminator is split into a non-linear feature map h (a temporal conv net over
(B, T, 263) normalised features, one feature vector per T/4 patch) and a last linear
layer w. SAN (Takida et al., ICLR 2024) normalises that layer, f(x) = <w/|w|, |w| h(x)>,
and trains its parts with different objectives:

* the direction w/|w| maximises the Wasserstein-like gap <w/|w|, E h(real) - E h(fake)>,
  i.e. it becomes the slice that best separates the two feature distributions;
* the feature map (and the scale |w|, which only rescales h) is trained with the hinge loss
  through logits in which the direction is held fixed.

With a single parameter w this split is exact: the gradient of w/|w| is orthogonal to w and
the gradient of |w| is parallel to it, so the two objectives update orthogonal components.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..motion.representation import FEATURE_DIM


@dataclass
class DiscriminatorConfig:
    feature_dim: int = FEATURE_DIM
    width: int = 128
    levels: int = 2               # stride-2 stages: patches cover 2**levels frames
    blocks_per_level: int = 2
    negative_slope: float = 0.2


@dataclass
class SANLogits:
    """Patch logits (B, T') for the discriminator update: `hinge` carries gradient to the
    feature map and scale only, `direction` to the direction only."""

    hinge: torch.Tensor
    direction: torch.Tensor


class ResidualConv(nn.Module):
    def __init__(self, width: int, dilation: int, slope: float):
        super().__init__()
        self.conv = nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation)
        self.mix = nn.Conv1d(width, width, 1)
        self.slope = slope

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv(F.leaky_relu(x, self.slope))
        return x + self.mix(F.leaky_relu(h, self.slope))


class SANDiscriminator(nn.Module):
    def __init__(self, config: DiscriminatorConfig | None = None):
        super().__init__()
        self.config = c = config or DiscriminatorConfig()
        if c.levels < 0 or c.width < 1 or c.blocks_per_level < 0:
            raise ValueError(f"bad discriminator config {c}")
        layers: list[nn.Module] = [nn.Conv1d(c.feature_dim, c.width, 3, padding=1)]
        for _ in range(c.levels):
            layers += [nn.LeakyReLU(c.negative_slope), nn.Conv1d(c.width, c.width, 4, stride=2, padding=1)]
            # growing dilations widen the receptive field to ~1 s without more downsampling
            layers += [ResidualConv(c.width, 3 ** k, c.negative_slope) for k in range(c.blocks_per_level)]
        layers.append(nn.LeakyReLU(c.negative_slope))
        self.features = nn.Sequential(*layers)
        self.weight = nn.Parameter(torch.randn(c.width) / c.width ** 0.5)

    @property
    def patch_frames(self) -> int:
        return 2 ** self.config.levels

    def patch_mask(self, valid: torch.Tensor) -> torch.Tensor:
        """(B, T) frame mask -> (B, T') patch mask: a patch counts if any of its frames is real."""
        return F.max_pool1d(valid.float().unsqueeze(1), self.patch_frames).squeeze(1) > 0

    def _scaled_features(self, x: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
        if x.ndim != 3 or x.shape[-1] != self.config.feature_dim:
            raise ValueError(f"expected features (B, T, {self.config.feature_dim}), got {tuple(x.shape)}")
        if x.shape[1] % self.patch_frames:
            raise ValueError(f"the discriminator needs a frame count divisible by {self.patch_frames}, "
                             f"got {x.shape[1]}")
        if valid is not None:
            # padding after a motion's end is not judged: zero it in real and fake alike
            x = x * valid.unsqueeze(-1).to(x.dtype)
        h = self.features(x.transpose(1, 2))                # (B, C, T')
        return h * self.weight.norm()

    def direction(self) -> torch.Tensor:
        return F.normalize(self.weight, dim=0)

    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Patch logits (B, T') with gradients to everything: the generator's view."""
        h = self._scaled_features(x, valid)
        return torch.einsum("bct,c->bt", h, self.direction().to(h.dtype))

    def san_logits(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> SANLogits:
        h = self._scaled_features(x, valid)
        w = self.direction().to(h.dtype)
        return SANLogits(hinge=torch.einsum("bct,c->bt", h, w.detach()),
                         direction=torch.einsum("bct,c->bt", h.detach(), w))


class PromptDiscriminator(nn.Module):
    """The SAN discriminator given the prompt, over frames (B, T, ...) of any per-frame shape (a
    denoiser's latents (B, T', parts, latent_dim), decoded features (B, T, 263)): the pooled text
    feature, projected, is appended to every frame, so a slow slash is judged against real slashes
    rather than against any real motion. config.feature_dim is replaced by this input's width."""

    def __init__(self, frame_dim: int, text_dim: int, config: DiscriminatorConfig | None = None,
                 text_channels: int = 32):
        super().__init__()
        self.text = nn.Linear(text_dim, text_channels)
        self.san = SANDiscriminator(replace(config or DiscriminatorConfig(), feature_dim=frame_dim + text_channels))

    def _valid(self, z: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
        """The frame mask on whole patches: the frames padded to fill the last one are not judged."""
        if valid is None:
            valid = torch.ones(z.shape[:2], dtype=torch.bool, device=z.device)
        return F.pad(valid, (0, -z.shape[1] % self.san.patch_frames), value=False)

    def _input(self, z: torch.Tensor, pooled: torch.Tensor, valid: torch.Tensor | None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        B, T = z.shape[:2]
        x = torch.cat((z.flatten(2), self.text(pooled.to(z.dtype))[:, None].expand(B, T, -1)), dim=-1)
        return F.pad(x, (0, 0, 0, -T % self.san.patch_frames)), self._valid(z, valid)

    def patch_mask(self, z: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
        return self.san.patch_mask(self._valid(z, valid))

    def forward(self, z: torch.Tensor, pooled: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        return self.san(*self._input(z, pooled, valid))

    def san_logits(self, z: torch.Tensor, pooled: torch.Tensor, valid: torch.Tensor | None = None) -> SANLogits:
        return self.san.san_logits(*self._input(z, pooled, valid))


def _masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def san_discriminator_loss(real: SANLogits, fake: SANLogits, mask: torch.Tensor | None = None
                           ) -> tuple[torch.Tensor, dict[str, float]]:
    """The discriminator's loss (to minimise): hinge terms for the feature map, and the
    negated Wasserstein gap E f(real) - E f(fake) for the direction. `mask` (B, T') drops
    patches that lie wholly in padding."""
    hinge = _masked_mean(F.relu(1.0 - real.hinge), mask) + _masked_mean(F.relu(1.0 + fake.hinge), mask)
    gap = _masked_mean(real.direction, mask) - _masked_mean(fake.direction, mask)
    loss = hinge - gap
    return loss, {"d_hinge": float(hinge.detach()), "d_gap": float(gap.detach()),
                  "d_real": float(_masked_mean(real.hinge.detach(), mask)),
                  "d_fake": float(_masked_mean(fake.hinge.detach(), mask))}


def san_generator_loss(fake_logits: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """-E f(fake): the generator raises the fakes' logits along the current slice."""
    return -_masked_mean(fake_logits, mask)
