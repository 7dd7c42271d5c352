"""The sampling loop: classifier-free guidance with all rows in one forward pass and a
per-step callback."""
from __future__ import annotations

from typing import Callable

import torch

from .schedule import STOCHASTIC_SAMPLERS, NoiseSchedule

# model(x (R, ...), t (R,)) -> model output (R, ...), R = rows of the batched forward.
ModelFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def cfg_combine(out: torch.Tensor, scale: float | torch.Tensor, rescale: float = 0.0) -> torch.Tensor:
    """The batched forward's rows are [unconditional..., conditional...]; mix them, at one scale
    or at each row's own (a tensor of B scales).
    rescale (phi, Lin et al. 2024) pulls each guided row's standard deviation towards its
    conditional row's: a large scale inflates the prediction, which averages gait phases."""
    uncond, cond = out.chunk(2, dim=0)
    if isinstance(scale, torch.Tensor):
        scale = scale.to(out).view(-1, *([1] * (out.ndim - 1)))
    elif scale == 1.0:
        return cond
    guided = uncond + scale * (cond - uncond)
    if rescale > 0:
        dims = tuple(range(1, out.ndim))
        matched = guided * (cond.std(dims, keepdim=True) / guided.std(dims, keepdim=True).clamp_min(1e-8))
        guided = rescale * matched + (1 - rescale) * guided
    return guided


def describe_settings(settings: dict) -> str:
    """Reports' words for a run's ddim_eta, cfg_rescale and cfg_cutoff (absent: the run predates them,
    eta 0, plain guidance at every step), its latent projections and planted-feet refinement (absent or 0:
    none) and its precision (absent: not recorded), e.g.
    " (eta 1, CFG rescale 0.7, no guidance below t = 300, 1 VAE projection, fp32)"; the consistency
    sampler has only the last three."""
    parts = []
    if settings.get("sampler") != "consistency":
        parts = [f"eta {settings.get('ddim_eta', 0.0):g}"] if settings.get("sampler", "ddim") == "ddim" else []
        if settings.get("sampler") in STOCHASTIC_SAMPLERS:
            parts.append("fresh noise at every step")
        parts.append(f"CFG rescale {settings.get('cfg_rescale', 0.0):g}")
        if settings.get("cfg_cutoff", 0.0) > 0:
            parts.append(f"no guidance below t = {settings['cfg_cutoff'] * 1000:g}")
    n = settings.get("projections", 0)
    if n:
        parts.append(f"{n} VAE projection{'s' if n > 1 else ''}")
    if settings.get("foot_refine", 0):
        parts.append(f"planted feet refined within {settings['foot_refine']} evaluations")
    if settings.get("precision"):
        parts.append(settings["precision"])
    return f" ({', '.join(parts)})" if parts else ""


def fresh_noise(x: torch.Tensor, generator: torch.Generator | list[torch.Generator] | None,
                shared: bool = False) -> torch.Tensor:
    """Standard normal noise shaped like x, drawn on the CPU so that a seed gives the same motion
    on every device. generator: one for all rows, or one per row (each row then draws exactly
    as it would alone); shared gives every row the same draw (edit branches from one z_T)."""
    shape = (1,) + tuple(x.shape[1:]) if shared else tuple(x.shape)
    if isinstance(generator, list):
        fresh = torch.cat([torch.randn((1,) + shape[1:], generator=g, dtype=x.dtype) for g in generator])
    else:
        fresh = torch.randn(shape, generator=generator, dtype=x.dtype)
    return fresh.to(x.device).expand_as(x)


@torch.no_grad()
def sample(model: ModelFn, noise: torch.Tensor, schedule: NoiseSchedule, sampler: str = "ddim", steps: int = 50,
           cfg_scale: float = 7.5, on_step: Callable[[int, int, torch.Tensor], None] | None = None,
           blend: Callable[[torch.Tensor], torch.Tensor] | None = None, eta: float = 0.0, cfg_rescale: float = 0.0,
           generator: torch.Generator | list[torch.Generator] | None = None,
           shared_noise: bool = False, cfg_cutoff: float = 0.0, start: int = 0,
           watch: Callable[[int, torch.Tensor], None] | None = None) -> torch.Tensor:
    """Denoise `noise` (B, ...) to clean latents.

    `model` receives 2B rows (unconditional rows first, then conditional ones) so that
    classifier-free guidance costs a single forward per step. `blend(x)` may change the
    latents after each step (an edit's held body parts); `on_step(i, n, x)` reports progress.
    eta > 0 ("ddim" only; 1 = ancestral) adds fresh noise at each step, drawn as fresh_noise
    draws it from `generator` (shared_noise: one draw for every row); "dpm-sde" always does.
    Steps at t < cfg_cutoff x T take the conditional prediction alone: by then the action is laid
    down, and guidance there mostly made the feet slide. If `model` has a `conditional` attribute
    (B rows -> their conditional prediction), those steps run it instead of the 2B-row forward.
    start > 0 ("ddim" only, whose steps keep no state) skips the first steps: `noise` is then a
    latent noised to schedule.sampler(sampler, steps).timesteps[start] (SDEdit).
    watch(i, x0) sees the guided prediction's clean estimate of step i (1-based) before the step is taken;
    an exception it raises ends the sampling (the pipeline stops a motion whose length already left its band).
    """
    if eta < 0 or (eta > 0 and sampler != "ddim"):
        raise ValueError(f"eta must be >= 0 and needs the ddim sampler, got eta={eta} with {sampler!r}")
    if start and sampler != "ddim":
        raise ValueError(f"only the ddim sampler can start part of the way down, not {sampler!r}")
    if not 0.0 <= cfg_cutoff < 1.0:
        raise ValueError(f"cfg_cutoff must be in [0, 1), got {cfg_cutoff}")
    sched = schedule.sampler(sampler, steps)
    if not 0 <= start < len(sched.timesteps):
        raise ValueError(f"start must be in 0..{len(sched.timesteps) - 1}, got {start}")
    unguided_below = cfg_cutoff * schedule.config.train_steps
    conditional = getattr(model, "conditional", None)
    x = noise
    timesteps = sched.timesteps
    for i, t in list(enumerate(timesteps))[start:]:
        tt = torch.full((2 * x.shape[0],), int(t), dtype=torch.long, device=x.device)
        guided = int(t) >= unguided_below
        if not guided and conditional is not None:
            out = conditional(x, tt[:x.shape[0]]).float()
        else:
            out = model(torch.cat((x, x), dim=0), tt)
            out = cfg_combine(out.float(), cfg_scale if guided else 1.0, cfg_rescale)
        if watch is not None:
            watch(i + 1, schedule.to_x0_eps(x, out, tt[:x.shape[0]])[0])
        if eta > 0 or sampler in STOCHASTIC_SAMPLERS:
            ddim = {"eta": eta} if eta > 0 else {}        # only DDIM takes eta (checked above)
            x = sched.step(out, t, x, variance_noise=fresh_noise(x, generator, shared_noise), **ddim).prev_sample
        else:
            x = sched.step(out, t, x).prev_sample
        if blend is not None:
            x = blend(x)
        if on_step is not None:
            on_step(i + 1, len(timesteps), x)
    return x
