"""Few-step sampling with a consistency-distilled student (latent consistency models, as
MotionLCM applies them to motion latents).

The student keeps the teacher's architecture and v-prediction output, plus the guidance
scale as a condition. Its consistency function maps a noisy latent at any timestep of the
teacher's 50-step DDIM grid straight to a clean latent:

    f(z_t, t) = c_skip(t) * z_t + c_out(t) * x0(z_t, v(z_t, t))

with diffusers' LCM boundary scalings (c_skip = 1, c_out = 0 at t = 0), so training
(salad/training/consistency_task.py) and sampling share one definition. Multistep sampling
alternates f with re-noising to the next, lower timestep.
"""
from __future__ import annotations

from typing import Callable

import torch

from .sampling import ModelFn, fresh_noise
from .schedule import CONSISTENCY_GRID, NoiseSchedule


def grid_timesteps(schedule: NoiseSchedule) -> torch.Tensor:
    """The teacher's DDIM grid the student is distilled along, ascending: k-1, 2k-1, ..., T-1
    with k = T / CONSISTENCY_GRID (19, 39, ..., 999); one distillation step skips k timesteps."""
    k = schedule.config.train_steps // CONSISTENCY_GRID
    return torch.arange(1, CONSISTENCY_GRID + 1) * k - 1


def sampler_timesteps(schedule: NoiseSchedule, max_steps: int = 4) -> list[int]:
    """Every timestep the consistency sampler evaluates the student at, over 1..max_steps steps
    (descending): 999, 759, 679, 499, 339, 259 for up to 4 steps."""
    ts = {int(t) for n in range(1, max_steps + 1) for t in schedule.sampler("consistency", n).timesteps}
    return sorted(ts, reverse=True)


def boundary_scalings(schedule: NoiseSchedule, t: torch.Tensor, like: torch.Tensor):
    """(c_skip, c_out) at timesteps t (B,), shaped to broadcast against `like`."""
    c_skip, c_out = schedule.boundary_scalings(t)
    shape = (-1,) + (1,) * (like.ndim - 1)
    return (c_skip.view(shape).to(like.device, like.dtype), c_out.view(shape).to(like.device, like.dtype))


def consistency_fn(schedule: NoiseSchedule, zt: torch.Tensor, out: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The clean latent the student's output `out` at (zt, t) stands for."""
    x0, _ = schedule.to_x0_eps(zt, out, t)
    c_skip, c_out = boundary_scalings(schedule, t, zt)
    return c_skip * zt + c_out * x0


@torch.no_grad()
def consistency_sample(model: ModelFn, noise: torch.Tensor, schedule: NoiseSchedule, steps: int = 4,
                       generator: torch.Generator | list[torch.Generator] | None = None, shared_noise: bool = False,
                       on_clean: Callable[[int, torch.Tensor], torch.Tensor] | None = None,
                       on_step: Callable[[int, int, torch.Tensor], None] | None = None,
                       start: int = 0) -> torch.Tensor:
    """Denoise `noise` (B, ...) in `steps` student evaluations. `model(x, t)` gets the B rows
    themselves (the guidance scale is part of the model, not a second batch half).

    generator: one for all rows, or a list of one per row (each row then re-noises exactly as it
    would alone). shared_noise re-noises every row with the same draw, so branches that started from one
    z_T (source and edited motion) stay comparable. on_clean(t, x0) may change the clean
    estimate made at timestep t before it is re-noised (guided control does, MPGD-style).
    start > 0 skips the first evaluations: `noise` is then a latent noised to the sampler's timesteps[start]."""
    sched = schedule.sampler("consistency", steps)
    ts = [int(t) for t in sched.timesteps]
    if not 0 <= start < len(ts):
        raise ValueError(f"start must be in 0..{len(ts) - 1}, got {start}")
    x = noise
    for i, t in list(enumerate(ts))[start:]:
        tt = torch.full((x.shape[0],), t, dtype=torch.long, device=x.device)
        x0 = consistency_fn(schedule, x, model(x, tt).float(), tt)
        if on_clean is not None:
            x0 = on_clean(t, x0)
        if i + 1 < len(ts):
            x = schedule.add_noise(x0, fresh_noise(x, generator, shared_noise), torch.full_like(tt, ts[i + 1]))
        else:
            x = x0
        if on_step is not None:
            on_step(i + 1, len(ts), x)
    return x
