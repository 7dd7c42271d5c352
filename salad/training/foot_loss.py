"""The feet's and the root's world velocity, reconstructed against real.

The reconstruction losses work per channel in normalised units, so a small error in the root
velocity or in a foot's root-relative position passes as small, yet adds up to a foot that
slides by centimetres a frame. These terms measure what an animator sees instead, from the
kinematics of both motions, in (m/s)^2: the feet where the real foot is planted, and the root
everywhere (without it, the cheapest way to plant the feet is to slow the whole walk down)."""
from __future__ import annotations

import torch

from ..motion import representation as rep
from ..motion import skeleton as sk

_JOINTS = (0,) + tuple(sk.CONTACT_JOINTS)      # root, then left ankle, left toe, right ankle, right toe


def _velocities(features: torch.Tensor) -> torch.Tensor:
    """Features (B, T, 263) in physical units -> (B, T-1, 5, 3) velocities in m/s of the root and
    the contact joints."""
    j = rep.features_to_joints(features)[:, :, list(_JOINTS), :]
    return (j[:, 1:] - j[:, :-1]) * rep.FPS


def velocity_errors(recon: torch.Tensor, real: torch.Tensor, valid: torch.Tensor, normalizer: rep.Normalizer,
                    weights: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """recon, real: normalised features (B, T, 263); valid (B, T) bool; weights (B,) per row.
    "foot": mean squared velocity error over the (frame, foot joint) pairs where the real motion's
    contact channel is set; "root": mean squared root velocity error over the valid frames."""
    with torch.autocast(recon.device.type, enabled=False):
        r = normalizer.denormalize(recon.float())
        x = normalizer.denormalize(real.float())
        err = (_velocities(r) - _velocities(x)).pow(2).sum(-1)                   # (B, T-1, 5)
        steps = (valid[:, :-1] & valid[:, 1:]).float()
        planted = (x[:, :-1, rep.CONTACT_SLICE] > 0.5).float() * steps[..., None]
        if weights is not None:
            w = weights.float().view(-1, 1)
            steps, planted = steps * w, planted * w[..., None]
        return {"foot": (err[..., 1:] * planted).sum() / planted.sum().clamp_min(1.0),
                "root": (err[..., 0] * steps).sum() / steps.sum().clamp_min(1.0)}


def planted_foot_error(recon: torch.Tensor, real: torch.Tensor, valid: torch.Tensor,
                       normalizer: rep.Normalizer, weights: torch.Tensor | None = None) -> torch.Tensor:
    """velocity_errors' "foot" term alone."""
    return velocity_errors(recon, real, valid, normalizer, weights)["foot"]
