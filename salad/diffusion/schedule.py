"""Noise schedule, training targets and samplers, built on diffusers' schedulers.

The model predicts v (Salimans & Ho): v = sqrt(a) * eps - sqrt(1 - a) * x0, with a the
cumulative alpha at t. Samplers are diffusers' DDIM (the paper's), DPM-Solver++ (a multistep
solver that needs far fewer steps), its SDE form "dpm-sde" (SDE-DPM-Solver++(2M): fresh noise at
every step like ancestral DDIM, whose first-order form it is; at 25 steps the fidelity table of
ancestral DDIM-50); "consistency" is diffusers' LCM schedule for a distilled student
(salad/diffusion/consistency.py).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from diffusers import DDIMScheduler, DDPMScheduler, DPMSolverMultistepScheduler, LCMScheduler

SAMPLERS = ("ddim", "dpm", "dpm-sde", "consistency")
# Samplers that draw fresh noise at every step whatever eta is.
STOCHASTIC_SAMPLERS = ("dpm-sde",)
# The student is distilled along the teacher's 50-step DDIM grid; it samples on that grid.
CONSISTENCY_GRID = 50


@dataclass
class DiffusionConfig:
    train_steps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    beta_schedule: str = "scaled_linear"
    prediction_type: str = "v_prediction"
    # "trailing" starts sampling at t = T-1, where the model was trained, instead of
    # the "leading" default that never visits the noisiest steps.
    timestep_spacing: str = "trailing"


class NoiseSchedule:
    def __init__(self, config: DiffusionConfig | None = None):
        self.config = c = config or DiffusionConfig()
        if c.prediction_type not in ("v_prediction", "epsilon", "sample"):
            raise ValueError(f"unknown prediction_type {c.prediction_type!r}")
        self._common = dict(num_train_timesteps=c.train_steps, beta_start=c.beta_start, beta_end=c.beta_end,
                            beta_schedule=c.beta_schedule, prediction_type=c.prediction_type)
        self.train_scheduler = DDPMScheduler(**self._common, clip_sample=False)
        self.alphas_cumprod = self.train_scheduler.alphas_cumprod.to(torch.float64)
        self._boundary: LCMScheduler | None = None

    # -- coefficients at integer timesteps, broadcast to x
    def _coef(self, t: torch.Tensor, like: torch.Tensor):
        a = self.alphas_cumprod.to(like.device)[t.long().cpu()].to(like.device)
        shape = (-1,) + (1,) * (like.ndim - 1)
        return a.sqrt().view(shape).to(like.dtype), (1 - a).sqrt().view(shape).to(like.dtype)

    def sample_timesteps(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        return torch.randint(0, self.config.train_steps, (n,), generator=generator)

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        sa, s1a = self._coef(t, x0)
        return sa * x0 + s1a * noise

    def remove_noise(self, xt: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The clean sample that add_noise turned into xt with `noise` (its inverse)."""
        sa, s1a = self._coef(t, xt)
        return (xt - s1a * noise) / sa

    def target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """What the model is trained to output."""
        p = self.config.prediction_type
        if p == "epsilon":
            return noise
        if p == "sample":
            return x0
        sa, s1a = self._coef(t, x0)
        return sa * noise - s1a * x0

    def to_x0_eps(self, xt: torch.Tensor, out: torch.Tensor, t: torch.Tensor):
        """The model output's estimates of the clean sample and the noise."""
        sa, s1a = self._coef(t, xt)
        p = self.config.prediction_type
        if p == "v_prediction":
            x0 = sa * xt - s1a * out
            eps = s1a * xt + sa * out
        elif p == "epsilon":
            eps, x0 = out, (xt - s1a * out) / sa
        else:
            x0, eps = out, (xt - sa * out) / s1a
        return x0, eps

    def from_x0_eps(self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The model output that corresponds to given clean-sample and noise estimates."""
        sa, s1a = self._coef(t, x0)
        p = self.config.prediction_type
        if p == "v_prediction":
            return sa * eps - s1a * x0
        return eps if p == "epsilon" else x0

    def boundary_scalings(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The consistency function's (c_skip, c_out) at timesteps t (B,), float64 on the CPU, from
        diffusers' LCM scheduler; it depends on no sampling state, so one instance serves every call
        (a fresh one cost about half a millisecond, at every step of a 4-step sampling)."""
        if self._boundary is None:
            self._boundary = self.sampler("consistency", 1)
        return self._boundary.get_scalings_for_boundary_condition_discrete(t.double().cpu())

    def sampler(self, name: str = "ddim", steps: int = 50, timesteps: list[int] | None = None):
        """A fresh diffusers scheduler with its timesteps set: `steps` of them spaced as configured,
        or exactly `timesteps` (descending; "dpm" only)."""
        if name not in SAMPLERS:
            raise ValueError(f"unknown sampler {name!r}; choose one of {', '.join(SAMPLERS)}")
        if not 1 <= int(steps) <= self.config.train_steps:
            raise ValueError(f"steps must be in 1..{self.config.train_steps}, got {steps}")
        spacing = self.config.timestep_spacing
        if name == "consistency":
            if int(steps) > CONSISTENCY_GRID:
                raise ValueError(f"the consistency sampler takes 1..{CONSISTENCY_GRID} steps, got {steps}")
            s = LCMScheduler(**self._common, original_inference_steps=CONSISTENCY_GRID, clip_sample=False,
                             set_alpha_to_one=False, timestep_spacing=spacing)
        elif name == "ddim":
            s = DDIMScheduler(**self._common, clip_sample=False, set_alpha_to_one=False, timestep_spacing=spacing)
        else:
            algorithm = "sde-dpmsolver++" if name == "dpm-sde" else "dpmsolver++"
            s = DPMSolverMultistepScheduler(**self._common, algorithm_type=algorithm, solver_order=2,
                                            timestep_spacing=spacing, lower_order_final=True)
        if timesteps is None:
            s.set_timesteps(int(steps))
        elif name != "dpm" or list(timesteps) != sorted(set(timesteps), reverse=True):
            raise ValueError(f"explicit timesteps need the dpm sampler and a strictly descending list, got {name!r}")
        else:
            s.set_timesteps(timesteps=[int(t) for t in timesteps])
        return s

    def to_dict(self) -> dict:
        return asdict(self.config)
