"""The sampling loop: classifier-free guidance with all rows in one forward pass and a
per-step callback."""
from __future__ import annotations

from typing import Callable

import torch

from .schedule import NoiseSchedule

# model(x (R, ...), t (R,)) -> model output (R, ...), R = rows of the batched forward.
ModelFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def cfg_combine(out: torch.Tensor, scale: float) -> torch.Tensor:
    """The batched forward's rows are [unconditional..., conditional...]; mix them."""
    uncond, cond = out.chunk(2, dim=0)
    if scale == 1.0:
        return cond
    return uncond + scale * (cond - uncond)


@torch.no_grad()
def sample(model: ModelFn, noise: torch.Tensor, schedule: NoiseSchedule, sampler: str = "ddim", steps: int = 50,
           cfg_scale: float = 7.5, on_step: Callable[[int, int, torch.Tensor], None] | None = None,
           blend: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Denoise `noise` (B, ...) to clean latents.

    `model` receives 2B rows (unconditional rows first, then conditional ones) so that
    classifier-free guidance costs a single forward per step. `blend(x)` may change the
    latents after each step (an edit's held body parts); `on_step(i, n, x)` reports progress.
    """
    sched = schedule.sampler(sampler, steps)
    x = noise
    timesteps = sched.timesteps
    for i, t in enumerate(timesteps):
        tt = torch.full((2 * x.shape[0],), int(t), dtype=torch.long, device=x.device)
        out = model(torch.cat((x, x), dim=0), tt)
        out = cfg_combine(out.float(), cfg_scale)
        x = sched.step(out, t, x).prev_sample
        if blend is not None:
            x = blend(x)
        if on_step is not None:
            on_step(i + 1, len(timesteps), x)
    return x
