"""Training-free guided sampling (MoLA §3.4, App. B): MPGD on the clean-latent estimate,
with time travel.

At every DDIM step the clean latent estimate z0|t is decoded through the VAE to
global joint positions, a loss against the control targets is differentiated back to
z0|t, and z0|t takes a gradient step before the deterministic DDIM update. Time
travel repeats a step r times: the updated sample is re-noised from t-1 back to t and
the network is run again on it (the public implementation reused the stale output).
"""
from __future__ import annotations

from typing import Callable

import torch

from .sampling import ModelFn, cfg_combine
from .schedule import NoiseSchedule


def step_size(t: int, strength: float, train_steps: int = 1000) -> float:
    """MoLA's schedule: largest in the middle of the diffusion, vanishing at both ends."""
    u = t / train_steps
    return 4.0 * strength * u * (1.0 - u)


def default_repeats(i: int, n: int) -> int:
    """Time-travel repeats per step: more where the layout forms, none at the end."""
    if i < 0.2 * n:
        return 1
    if i < 0.6 * n:
        return 3
    if i < 0.8 * n:
        return 2
    return 1


def guided_sample(model: ModelFn, noise: torch.Tensor, schedule: NoiseSchedule, loss_fn: Callable,
                  steps: int = 50, cfg_scale: float = 7.5, strength: float = 1.0,
                  repeats: Callable[[int, int], int] | int = default_repeats, generator: torch.Generator | None = None,
                  on_step: Callable[[int, int, torch.Tensor], None] | None = None) -> torch.Tensor:
    """DDIM (eta = 0) with MPGD guidance. loss_fn(z0) -> scalar, differentiable in z0."""
    sched = schedule.sampler("ddim", steps)
    ts = [int(t) for t in sched.timesteps]
    abar = schedule.alphas_cumprod
    final = float(abar[0])                       # the scheduler's set_alpha_to_one=False end point
    x = noise
    rep = (lambda i, n: repeats) if isinstance(repeats, int) else repeats
    for i, t in enumerate(ts):
        a_t = float(abar[t])
        a_prev = float(abar[ts[i + 1]]) if i + 1 < len(ts) else final
        tt = torch.full((x.shape[0],), t, dtype=torch.long)
        r = max(1, int(rep(i, len(ts))))
        for k in range(r):
            with torch.no_grad():
                out = cfg_combine(model(torch.cat((x, x)), torch.cat((tt, tt))).float(), cfg_scale)
                z0, eps = schedule.to_x0_eps(x, out, tt)
            rho = step_size(t, strength, schedule.config.train_steps)
            if rho > 0:
                with torch.enable_grad():
                    z = z0.detach().requires_grad_(True)
                    grad, = torch.autograd.grad(loss_fn(z), z)
                z0 = z0 - rho * grad
            x_prev = a_prev ** 0.5 * z0 + (1 - a_prev) ** 0.5 * eps
            if k < r - 1:
                # time travel: back to t with fresh noise, then denoise again with a new prediction
                ratio = a_t / a_prev
                fresh = torch.randn(x.shape, generator=generator, dtype=x.dtype)
                x = ratio ** 0.5 * x_prev + (1 - ratio) ** 0.5 * fresh
        x = x_prev.detach()
        if on_step is not None:
            on_step(i + 1, len(ts), x)
    return x
