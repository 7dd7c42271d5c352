"""DDIM inversion of clean latents, with corrections for classifier-free guidance.

Sampling runs deterministic DDIM steps F_i: x_i -> x_{i+1} from z_T = x_0 to z_0 = x_n
(i counts steps; timestep t_i falls as i grows). Inverting a real motion means finding
a trajectory whose last point is its VAE latent. The methods:

* ``ddim``: the textbook inversion at cfg 1 (the model's output at x_{i+1} stands in for
  the one at x_i). Sampling back at cfg 7.5 drifts away: guidance was not inverted.
* ``negative``: the same trajectory, sampled back with the source prompt as the
  "unconditional" prompt, so guidance cancels out for the source (negative-prompt
  inversion); edits are guided by the difference between target and source.
* ``null_text``: the cfg-1 trajectory as a pivot, then per step the unconditional text
  tokens are optimised so the guided step lands on the pivot (null-text inversion).
* ``fixed_point``: each step at full guidance solved exactly, x_i = G(x_i), by a few
  fixed-point iterations per step.

Any trajectory can also be followed exactly: with ``correct=True`` the sampler adds, at
each step, the difference between the stored trajectory and the source branch's step;
every other branch (the edit) receives the same per-step correction.
"""
from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Callable

import torch

from ..models.text import TextFeatures
from ..progress import Progress
from .sampling import cfg_combine
from .schedule import NoiseSchedule

METHODS = ("ddim", "negative", "null_text", "fixed_point")


# ---------------------------------------------------------------- the DDIM grid

@dataclass
class DDIMGrid:
    """The sampler's timesteps and where each step lands, exactly as diffusers' DDIM
    scheduler steps them (including its rule for the step's target)."""

    timesteps: list[int]          # t_i, descending
    targets: list[int]            # timestep x_{i+1} sits at (0 for the final one)

    @property
    def steps(self) -> int:
        return len(self.timesteps)


def ddim_grid(schedule: NoiseSchedule, steps: int) -> DDIMGrid:
    sched = schedule.sampler("ddim", steps)
    stride = sched.config.num_train_timesteps // sched.num_inference_steps
    ts = [int(t) for t in sched.timesteps]
    # the last step lands on alpha-bar at t=0 (set_alpha_to_one=False): the model's own t=0
    targets = [max(t - stride, 0) for t in ts]
    if float(sched.alphas_cumprod[0]) != float(sched.final_alpha_cumprod):
        raise ValueError("inversion needs a DDIM schedule whose final alpha is alpha-bar(0)")
    return DDIMGrid(ts, targets)


# The steps below run in float64 (the schedule's maths on float64 tensors): inversion
# accumulates every step's rounding.

def _at(t: int) -> torch.Tensor:
    return torch.tensor([int(t)])


def noise_estimate(schedule: NoiseSchedule, x: torch.Tensor, out: torch.Tensor, t: int) -> torch.Tensor:
    """The noise that a model output at timestep t implies for x."""
    return schedule.to_x0_eps(x.double(), out.double(), _at(t))[1]


def ddim_step(schedule: NoiseSchedule, x: torch.Tensor, out: torch.Tensor, t: int, t_next: int) -> torch.Tensor:
    """One deterministic DDIM step (eta = 0) from t to t_next, the same update as diffusers' DDIMScheduler."""
    x0, eps = schedule.to_x0_eps(x.double(), out.double(), _at(t))
    return schedule.add_noise(x0, eps, _at(t_next)).to(x.dtype)


def renoise(schedule: NoiseSchedule, x_next: torch.Tensor, eps: torch.Tensor, t: int, t_next: int) -> torch.Tensor:
    """The x at timestep t that a DDIM step with noise estimate eps takes to x_next (at t_next)."""
    eps = eps.double()
    x0 = schedule.remove_noise(x_next.double(), eps, _at(t_next))
    return schedule.add_noise(x0, eps, _at(t)).to(x_next.dtype)


# ---------------------------------------------------------------- the denoiser as inversion sees it

class Denoise:
    """The pipeline's denoiser on fixed-length latents, rows [unconditional..., conditional...].

    fp32=True runs without bf16 autocast: inversion accumulates the model's rounding over
    every step, so it and the sampling that replays it use the same precision.
    """

    def __init__(self, pipe, fp32: bool = True):
        self.pipe, self.fp32 = pipe, fp32
        self.schedule = pipe.schedule
        self.calls = 0

    def __call__(self, x: torch.Tensor, t: int, text: TextFeatures) -> torch.Tensor:
        self.calls += 1
        n = x.shape[0]
        if len(text) != n:
            raise ValueError(f"{len(text)} text rows for {n} latent rows")
        ctx = nullcontext() if self.fp32 else self.pipe.autocast(n)     # the pipeline's own rule (bf16_min_rows)
        with ctx:
            out = self.pipe.denoiser(x, torch.full((n,), int(t), dtype=torch.long, device=x.device), text.tokens,
                                     text.mask, None, pooled_text=text.pooled,
                                     auto_length=torch.zeros(n, dtype=torch.bool, device=x.device))
        return out.float()

    def guided(self, x: torch.Tensor, t: int, text: TextFeatures, cfg: float) -> torch.Tensor:
        """The guided output for B latents; text has 2B rows (unconditional first).
        At cfg 1 only the conditional rows run."""
        B = x.shape[0]
        if cfg == 1.0:
            return self(x, t, rows(text, slice(B, 2 * B)))
        return cfg_combine(self(torch.cat((x, x)), t, text), cfg)


def rows(text: TextFeatures, sel) -> TextFeatures:
    """A row subset of batched text features (a slice or a list of row indices)."""
    idx = list(range(len(text)))[sel] if isinstance(sel, slice) else list(sel)
    t = torch.tensor(idx, dtype=torch.long, device=text.tokens.device)
    return TextFeatures(text.tokens[t], text.mask[t], text.token_words[t], [text.words[i] for i in idx],
                        text.pooled[t])


def with_uncond(text: TextFeatures, uncond_rows: list[int], tokens: torch.Tensor | None) -> TextFeatures:
    """text with the leading tokens of `uncond_rows` replaced by `tokens` (n, D), e.g. a
    per-step optimised null-text embedding; None leaves the text as it is."""
    if tokens is None:
        return text
    new = text.tokens.clone()
    new[uncond_rows, : tokens.shape[0]] = tokens.to(new.dtype)
    return TextFeatures(new, text.mask, text.token_words, text.words, text.pooled)


# ---------------------------------------------------------------- the result

@dataclass
class Inversion:
    """A motion latent and the DDIM trajectory that leads to it.

    trajectory[i] is the input of sampling step i: trajectory[0] = z_T, trajectory[-1] =
    z_0 (the VAE's mean latent, scaled). `uncond` holds the per-step unconditional token
    features of null-text inversion (None otherwise).
    """

    method: str
    prompt: str
    cfg: float
    grid: DDIMGrid
    trajectory: torch.Tensor       # (steps + 1, 1, T/4, parts, latent_dim) float32
    uncond: list[torch.Tensor] | None = None
    fp32: bool = True
    seconds: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def z0(self) -> torch.Tensor:
        return self.trajectory[-1]

    @property
    def z_T(self) -> torch.Tensor:
        return self.trajectory[0]

    @property
    def steps(self) -> int:
        return self.grid.steps

    @property
    def latent_frames(self) -> int:
        return int(self.trajectory.shape[2])

    @property
    def negative(self) -> bool:
        """Whether the source prompt takes the unconditional rows when sampling back."""
        return self.method == "negative"


# ---------------------------------------------------------------- the methods

def _check(method: str, steps, cfg) -> None:
    if method not in METHODS:
        raise ValueError(f"inversion method must be one of {', '.join(METHODS)}, got {method!r}")
    if not isinstance(steps, int) or isinstance(steps, bool) or not 2 <= steps <= 1000:
        raise ValueError(f"steps must be an integer in 2..1000, got {steps!r}")
    if not isinstance(cfg, (int, float)) or not math.isfinite(cfg) or not 0 <= cfg <= 30:
        raise ValueError(f"cfg must be a number in 0..30, got {cfg!r}")


def _ddim_inversion(model: Denoise, z0: torch.Tensor, text: TextFeatures, grid: DDIMGrid, cfg: float,
                    tick: Callable[[], None]) -> torch.Tensor:
    """Textbook DDIM inversion: step i is undone with the model's output at x_{i+1}."""
    n = grid.steps
    traj = [z0]
    x = z0
    for i in reversed(range(n)):
        t, t_next = grid.timesteps[i], grid.targets[i]
        eps = noise_estimate(model.schedule, x, model.guided(x, t_next, text, cfg), t_next)
        x = renoise(model.schedule, x, eps, t, t_next)
        traj.append(x)
        tick()
    return torch.stack(traj[::-1])


def _fixed_point_inversion(model: Denoise, z0: torch.Tensor, text: TextFeatures, grid: DDIMGrid, cfg: float,
                           iterations: int, tol: float, tick: Callable[[], None]) -> tuple[torch.Tensor, dict]:
    """Solve F_i(x_i) = x_{i+1} at full guidance per step: x <- renoise(x_{i+1}, eps(x)).

    The first guess reuses the noise estimate of the step solved before (no extra
    forward); the iteration contracts fast because renoise scales eps by the small
    difference of two noise levels.
    """
    n = grid.steps
    traj = [z0]
    x_next, eps = z0, None
    residuals, used = [], []
    for i in reversed(range(n)):
        t, t_next = grid.timesteps[i], grid.targets[i]
        if eps is None:
            eps = noise_estimate(model.schedule, x_next, model.guided(x_next, t_next, text, cfg), t_next)
        x = renoise(model.schedule, x_next, eps, t, t_next)
        change = float("nan")
        k = 0
        for k in range(1, iterations + 1):
            eps = noise_estimate(model.schedule, x, model.guided(x, t, text, cfg), t)
            x_new = renoise(model.schedule, x_next, eps, t, t_next)
            change = float((x_new - x).norm() / x_new.norm().clamp_min(1e-12))
            x = x_new
            if change < tol:
                break
        residuals.append(change)
        used.append(k)
        traj.append(x)
        x_next = x
        tick()
    return torch.stack(traj[::-1]), {"fixed_point_last_change_max": max(residuals),
                                     "fixed_point_iterations_mean": sum(used) / len(used)}


def _null_text_inversion(model: Denoise, pivot: torch.Tensor, text: TextFeatures, grid: DDIMGrid, cfg: float,
                         inner: int, lr: float, tick: Callable[[], None]) -> tuple[list[torch.Tensor], dict]:
    """Per step, Adam on the unconditional token features so that the guided step from the
    current latent lands on the pivot trajectory; the latent then moves on with them."""
    n_tok = int(text.mask[0].sum())
    u = text.tokens[0, :n_tok].clone()
    cond = rows(text, [1])
    x = pivot[0]
    out_u, losses = [], []
    for i in range(grid.steps):
        t, t_next = grid.timesteps[i], grid.targets[i]
        target = pivot[i + 1].double()
        with torch.no_grad():
            c_out = model(x, t, cond)
        u = u.detach().requires_grad_(True)
        # the step size shrinks along the trajectory as the steps themselves do
        opt = torch.optim.Adam([u], lr=lr * (1.0 - i / (2.0 * grid.steps)))
        # early-stop threshold: the latent error that matters grows with the noise level
        threshold = 1e-5 + 2e-5 * (grid.steps - i) / grid.steps
        for j in range(inner + 1):
            with torch.enable_grad():
                u_out = model(x, t, with_uncond(rows(text, [0]), [0], u))
                guided = u_out + cfg * (c_out - u_out)
                x_new = ddim_step(model.schedule, x, guided, t, t_next)
                loss = torch.mean((x_new.double() - target) ** 2)
                if j == inner or loss.item() < threshold:
                    break
                opt.zero_grad()
                loss.backward()
            opt.step()
        losses.append(loss.item())
        out_u.append(u.detach().clone())
        x = x_new.detach()
        tick()
    return out_u, {"null_text_final_loss_max": max(losses), "null_text_final_loss_mean": sum(losses) / len(losses)}


@torch.no_grad()
def invert(pipe, z0: torch.Tensor, prompt: str, method: str, steps: int = 50, cfg: float = 7.5,
           fp32: bool = True, iterations: int = 4, tol: float = 1e-4, inner: int = 10, lr: float = 5e-2,
           progress: Progress | None = None) -> Inversion:
    """Invert a clean, scaled latent z0 (1, T/4, parts, D) under `prompt`.

    method: one of METHODS. cfg is the guidance the trajectory will be sampled back
    with. fixed_point: up to `iterations` iterations per step, stopping when the
    relative change falls below `tol`. null_text: up to `inner` Adam steps (learning
    rate `lr`) per diffusion step.
    """
    _check(method, steps, cfg)
    for name, value, low in (("iterations", iterations, 1), ("inner", inner, 0)):
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= 100:
            raise ValueError(f"{name} must be an integer in {low}..100, got {value!r}")
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0 and tol > 0):
        raise ValueError(f"lr and tol must be positive numbers, got lr={lr!r}, tol={tol!r}")
    if z0.ndim != 4 or z0.shape[0] != 1:
        raise ValueError(f"expected one latent (1, frames, parts, dim), got {tuple(z0.shape)}")
    prompt = pipe.check_prompt(prompt)
    if method == "null_text" and not pipe.denoiser.config.cross_attention:
        raise ValueError("null-text inversion optimises the text tokens a denoiser cross-attends to; "
                         "this denoiser has no cross-attention")
    start = time.perf_counter()
    grid = ddim_grid(pipe.schedule, steps)
    model = Denoise(pipe, fp32=fp32)
    text = pipe.encode_text(["", prompt])
    total = steps * (2 if method == "null_text" else 1)
    done = [0]

    def tick():
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    z0 = z0.float()
    uncond, info = None, {}
    if method == "fixed_point":
        traj, info = _fixed_point_inversion(model, z0, text, grid, cfg, iterations, tol, tick)
    else:
        traj = _ddim_inversion(model, z0, text, grid, 1.0, tick)
        if method == "null_text":
            # gradients flow to the text tokens only (the pipeline's weights are frozen)
            uncond, info = _null_text_inversion(model, traj, text, grid, cfg, inner, lr, tick)
    info["model_calls"] = model.calls
    return Inversion(method, prompt, float(cfg), grid, traj.float(), uncond, fp32,
                     time.perf_counter() - start, info)


# ---------------------------------------------------------------- sampling back

@torch.no_grad()
def sample_grid(pipe, x: torch.Tensor, grid: DDIMGrid, text: TextFeatures, cfg: float, from_step: int = 0,
                uncond: list[torch.Tensor] | None = None, trajectory: torch.Tensor | None = None, controller=None,
                fp32: bool = True, progress: Progress | None = None) -> torch.Tensor:
    """DDIM steps from_step..n-1 on B latents x (B, ...); text has 2B rows,
    [unconditional x B, conditional x B], branch 0 being the source.

    uncond: per-step unconditional token features (null-text inversion). trajectory:
    (n + 1, 1, ...) points branch 0 must pass through; each step's correction (the
    trajectory minus branch 0's step) is added to every branch.
    """
    B = x.shape[0]
    if len(text) != 2 * B:
        raise ValueError(f"expected {2 * B} text rows ([unconditional, conditional] per branch), got {len(text)}")
    if not 0 <= from_step < grid.steps:
        raise ValueError(f"from_step must be in 0..{grid.steps - 1}, got {from_step}")
    model = Denoise(pipe, fp32=fp32)
    uncond_rows = list(range(B))
    with pipe.denoiser.controlled(controller):
        for i in range(from_step, grid.steps):
            step_text = with_uncond(text, uncond_rows, uncond[i] if uncond is not None else None)
            out = cfg_combine(model(torch.cat((x, x)), grid.timesteps[i], step_text), cfg)
            x = ddim_step(model.schedule, x, out, grid.timesteps[i], grid.targets[i])
            if trajectory is not None:
                x = x + (trajectory[i + 1] - x[:1])
            if progress is not None:
                progress(i + 1 - from_step, grid.steps - from_step)
    return x


def replay(pipe, inv: Inversion, text: TextFeatures, controller=None, correct: bool = False,
           progress: Progress | None = None) -> torch.Tensor:
    """Sample B branches back from the inversion's z_T (text: 2B rows, source first) with
    the guidance, precision and per-step null-text tokens the inversion was made for.
    correct=True makes the source branch follow the trajectory exactly and gives every
    branch the same per-step corrections. Returns the final latents (B, ...)."""
    B = len(text) // 2
    x = inv.z_T.expand(B, *inv.z_T.shape[1:]).clone()
    return sample_grid(pipe, x, inv.grid, text, inv.cfg, uncond=inv.uncond,
                       trajectory=inv.trajectory if correct else None, controller=controller, fp32=inv.fp32,
                       progress=progress)
