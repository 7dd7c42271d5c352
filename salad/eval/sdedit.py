"""SDEdit, the baseline real-motion editing is compared with (salad eval-real-edit): the motion's
latent is noised part of the way and denoised under the new prompt, with no inversion."""
from __future__ import annotations

import math

import torch

from ..diffusion.inversion import ddim_grid, sample_grid
from ..editing.real import decode, encode
from ..motion.motion import Motion
from ..motion.real import RealMotion, load_real_motion, resolve_bone_lengths


def sdedit(pipe, motion, prompt: str, strength: float = 0.5, seed: int = 0, steps: int = 50, cfg: float = 7.5,
           fp32: bool = True, bone_lengths=None, trim: bool = False) -> Motion:
    """SDEdit: noise the motion's latent to timestep ~strength*T and denoise it under `prompt`."""
    if not isinstance(strength, (int, float)) or not math.isfinite(strength) or not 0 < strength <= 1:
        raise ValueError(f"strength must be in (0, 1], got {strength!r}")
    prompt = pipe.check_prompt(prompt)
    steps, cfg, _, _ = pipe.check_sampling(steps, cfg, "ddim")
    if not isinstance(motion, RealMotion):
        motion = load_real_motion(motion, pipe.canvas_frames, resolve_bone_lengths(pipe.source, bone_lengths),
                                  trim=trim)
    real = motion
    z0 = encode(pipe, real)
    grid = ddim_grid(pipe.schedule, steps)
    level = strength * pipe.schedule.config.train_steps
    first = next((i for i, t in enumerate(grid.timesteps) if t < level), grid.steps - 1)
    x = pipe.schedule.add_noise(z0, pipe.noise(1, real.frames, seed), torch.tensor([grid.timesteps[first]]))
    z = sample_grid(pipe, x, grid, pipe.encode_text(["", prompt]), cfg, from_step=first, fp32=fp32)
    m = decode(pipe, z, [prompt])[0]
    m.seed = seed
    m.info.update(sdedit_strength=strength, sdedit_timestep=grid.timesteps[first])
    return m
