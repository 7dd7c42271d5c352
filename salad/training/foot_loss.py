"""The feet's world velocity, reconstructed against real, where the real foot is planted.

The reconstruction losses work per channel in normalised units, so a small error in the root
velocity or in a foot's root-relative position passes as small, yet adds up to a foot that
slides by centimetres a frame. This term measures what an animator sees instead: the world
velocity of ankles and toes, from the kinematics of both motions, in (m/s)^2."""
from __future__ import annotations

import torch

from ..motion import representation as rep
from ..motion import skeleton as sk


def foot_velocities(features: torch.Tensor) -> torch.Tensor:
    """Features (B, T, 263) in physical units -> (B, T-1, 4, 3) velocities in m/s of the contact
    joints (left ankle, left toe, right ankle, right toe)."""
    feet = rep.features_to_joints(features)[:, :, list(sk.CONTACT_JOINTS), :]
    return (feet[:, 1:] - feet[:, :-1]) * rep.FPS


def planted_foot_error(recon: torch.Tensor, real: torch.Tensor, valid: torch.Tensor,
                       normalizer: rep.Normalizer, weights: torch.Tensor | None = None) -> torch.Tensor:
    """recon, real: normalised features (B, T, 263); valid (B, T) bool. Mean squared velocity
    error over the (frame, foot joint) pairs where the real motion's contact channel is set;
    weights (B,) weigh each row's pairs."""
    with torch.autocast(recon.device.type, enabled=False):
        r = normalizer.denormalize(recon.float())
        x = normalizer.denormalize(real.float())
        err = (foot_velocities(r) - foot_velocities(x)).pow(2).sum(-1)            # (B, T-1, 4)
        planted = (x[:, :-1, rep.CONTACT_SLICE] > 0.5) & (valid[:, :-1] & valid[:, 1:])[..., None]
        planted = planted.float()
        if weights is not None:
            planted = planted * weights.float().view(-1, 1, 1)
        return (err * planted).sum() / planted.sum().clamp_min(1.0)
