"""Latent consistency distillation (LCM; MotionLCM for motion) of the trained denoiser.

Each step draws a clean latent batch as denoiser training does, a timestep t of the teacher's
50-step DDIM grid and a guidance scale w per sample. The teacher, with classifier-free guidance
at w (both rows in one forward), takes one DDIM step from z_t to z_s, s = t - 20; the student's
consistency function at (z_t, t) learns to match the target network's at (z_s, s). The target
network is an EMA of the student (decay 0.95) and is what gets exported. The student starts as
a copy of the teacher with a zero-initialised guidance embedding, so at step 0 it is the
teacher without guidance.

With target = "trajectory" the teacher instead solves each noise draw from t = T-1 to the end,
and the student's consistency function at the timesteps the 1-4 step sampler visits regresses
that solution: the consistency function by its definition, with no bootstrap chain to
propagate. One solve costs about as much as 25 LCD steps' teacher calls, so its states are
replayed for a few optimiser steps from a small buffer of recent solves.

Regressing a deterministic solve teaches the student the teacher's probability-flow ODE, whose
motions are tamer than those of the stochastic sampler the studio uses (slower slashes, lower
kicks). With lambda_adv > 0 a discriminator conditioned on the prompt also judges the student's
clean estimates against the real latents of the same batch (or, with adversarial_real = "teacher",
the teacher's own stochastic samples of the same prompts and lengths), or both decoded by the frozen
VAE with adversarial_space = "motion", where the root's velocity is a channel of its own; the
student is pushed towards them. focus_max_clips > 0 has it judge the rare actions' rows alone,
focus_classes those of the named actions; focus_rows gives those actions rows of every solved batch.
"""
from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.func import functional_call

from ..checkpoint import CheckpointError, load_state_strict
from ..config import ConfigError, from_dict, to_dict, validate
from ..data.captions import crossover
from ..diffusion.consistency import consistency_fn, grid_timesteps, sampler_timesteps
from ..diffusion.sampling import cfg_combine, fresh_noise
from ..diffusion.schedule import CONSISTENCY_GRID, DiffusionConfig, NoiseSchedule
from ..models.denoiser import Denoiser
from ..models.discriminator import PromptDiscriminator, san_discriminator_loss, san_generator_loss
from ..models.io import (load_consistency_student, load_denoiser, partner_mismatches, save_denoiser,
                         vae_latent_checksums, vae_latent_origin)
from ..models.vae import MotionVAE
from .configs import ADVERSARIAL_REAL, CONSISTENCY_TARGETS, ConsistencyTrainConfig, DenoiserTrainConfig
from .denoiser_task import DenoiserTask


COND_KEYS = ("text", "text_mask", "frame_mask", "pooled", "auto", "text2", "text_mask2", "pooled2", "guidance")
# what a solve is made from, kept with it so a training state can save the replay buffer: a solve's states (one
# per sampler timestep, ~70 MB for a batch of 32) are solved again on resume rather than saved. text, text_mask and
# pooled are the second half of their "2" keys (the conditional rows after the unconditional ones); latents are
# kept only where they are the discriminator's real side (~1.4 MB a solve)
SOLVE_INPUTS = ("noise", "latents", "sde_seed", "text2", "text_mask2", "pooled2", "frame_mask", "auto", "guidance",
                "adversarial_rows")


class ConsistencyTraining(nn.Module):
    def __init__(self, teacher: Denoiser, schedule: NoiseSchedule, target_decay: float, huber_c: float,
                 objective: str = "lcd", teacher_steps: int = 25, replay_buffer: int = 16,
                 cfg_rescale: float = 0.0, cfg_cutoff: float = 0.0, student: Denoiser | None = None,
                 discriminator: PromptDiscriminator | None = None, lambda_adv: float = 0.0,
                 decoder: MotionVAE | None = None, latent_scale: float = 1.0, adversarial_real: str = "data"):
        """student: where the student starts (e.g. a narrower one than the teacher, so it stays fast);
        None: the teacher's architecture and weights with a zero guidance embedding. discriminator:
        needed when lambda_adv > 0; decoder (the frozen VAE, its latents scaled by latent_scale for
        the denoiser): the discriminator judges decoded motion instead of latents. adversarial_real:
        what the discriminator takes as real, the batch's latents ("data") or the teacher's stochastic
        samples of its prompts ("teacher"; trajectory objective only)."""
        super().__init__()
        if lambda_adv < 0 or (lambda_adv > 0 and discriminator is None):
            raise ValueError(f"lambda_adv must be >= 0, and a discriminator is needed above 0 (got {lambda_adv})")
        if adversarial_real not in ADVERSARIAL_REAL or (adversarial_real == "teacher" and objective != "trajectory"):
            raise ValueError(f"adversarial_real must be one of {', '.join(ADVERSARIAL_REAL)}, and \"teacher\" "
                             f"needs the trajectory objective (got {adversarial_real!r} with {objective!r})")
        if objective not in CONSISTENCY_TARGETS:
            raise ValueError(f"unknown consistency target {objective!r}; "
                             f"choose one of {', '.join(CONSISTENCY_TARGETS)}")
        if student is None:
            cfg = copy.deepcopy(teacher.config)
            cfg.guidance_embedding = True
            student = Denoiser(cfg)
            missing, unexpected = student.load_state_dict(teacher.state_dict(), strict=False)
            if unexpected or any(not k.startswith("guidance_mlp.") for k in missing):
                raise CheckpointError(f"the student does not fit the teacher (missing {missing}, "
                                      f"unexpected {unexpected})")
        self.student = student
        self.target = copy.deepcopy(self.student).requires_grad_(False)
        # The teacher and the decoder come from the teacher's directory at every start, so they are held
        # outside the registered modules: a training state (~55 MB) would otherwise carry their ~12 MB of
        # weights at every checkpoint. _apply still moves them with the rest.
        object.__setattr__(self, "teacher", teacher.requires_grad_(False))
        self.schedule, self.target_decay, self.huber_c = schedule, target_decay, huber_c
        # the teacher's guidance as its sampler applies it (sampling.sample), so that the student
        # learns the teacher's motions as the studio gets them
        self.cfg_rescale, self.unguided_below = cfg_rescale, cfg_cutoff * schedule.config.train_steps
        self.k = schedule.config.train_steps // CONSISTENCY_GRID
        self.objective = objective
        # trajectory: the student learns at the sampler's own timesteps; the teacher's solve passes
        # through each of them
        self.points = sampler_timesteps(schedule)
        even = [int(t) for t in schedule.sampler("dpm", teacher_steps).timesteps]
        self.solve_timesteps = sorted(set(even) | set(self.points), reverse=True)
        self.teacher_steps = teacher_steps
        self.replay_buffer = replay_buffer
        self._solves: list[dict] = []      # recent teacher solves
        self._unsolved: list[dict] = []    # a resumed run's buffer, as SOLVE_INPUTS, until its next step
        self.disc, self.lambda_adv = (discriminator, float(lambda_adv)) if lambda_adv > 0 else (None, 0.0)
        object.__setattr__(self, "decoder",
                           decoder.requires_grad_(False) if decoder is not None and self.disc is not None else None)
        self.latent_scale = latent_scale
        self.adversarial_real = adversarial_real

    def _apply(self, fn, recurse=True):
        for frozen in (self.teacher, self.decoder):
            if frozen is not None:
                frozen._apply(fn, recurse)
        return super()._apply(fn, recurse)

    @staticmethod
    def upgrade_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """A training state of an earlier version, which saved the teacher's and the decoder's weights
        too, as this one saves it."""
        return {k: v for k, v in state.items() if not k.startswith(("teacher.", "decoder."))}

    def train(self, mode: bool = True):
        super().train(mode)
        self.teacher.eval()      # dropout off: they give targets, not gradients
        self.target.eval()
        if self.decoder is not None:
            self.decoder.eval()
        return self

    @torch.no_grad()
    def update_target(self) -> None:
        for pt, ps in zip(self.target.parameters(), self.student.parameters()):
            pt.lerp_(ps.detach(), 1.0 - self.target_decay)

    @staticmethod
    def _student_cond(batch: dict) -> dict:
        return dict(text=batch["text"], text_mask=batch["text_mask"], frame_mask=batch["frame_mask"],
                    pooled_text=batch["pooled"], auto_length=batch["auto"])

    def _guided(self, zt: torch.Tensor, t: torch.Tensor, batch: dict) -> torch.Tensor:
        """The teacher's output with classifier-free guidance at each row's own scale (one forward),
        rescaled, and none below the cutoff."""
        fm = batch["frame_mask"]
        if bool((t < self.unguided_below).all()):
            # unguided, the mix is the conditional rows' output: the solve's last steps need half the rows
            B = zt.shape[0]     # the conditional rows are the second half, as cfg_combine reads them
            return self.teacher(zt, t, batch["text2"][B:], batch["text_mask2"][B:], fm,
                                pooled_text=batch["pooled2"][B:], auto_length=batch["auto"]).float()
        out = self.teacher(torch.cat((zt, zt)), torch.cat((t, t)), batch["text2"], batch["text_mask2"],
                           None if fm is None else torch.cat((fm, fm)), pooled_text=batch["pooled2"],
                           auto_length=torch.cat((batch["auto"], batch["auto"]))).float()
        scale = torch.where(t >= self.unguided_below, batch["guidance"].to(out), 1.0)
        return cfg_combine(out, scale, self.cfg_rescale)

    def _huber(self, pred: torch.Tensor, target: torch.Tensor, fm: torch.Tensor | None) -> torch.Tensor:
        err = torch.sqrt((pred - target) ** 2 + self.huber_c ** 2) - self.huber_c
        err = err.mean(dim=(2, 3))                           # (B, latent frames)
        if fm is None:
            return err.mean()
        m = fm.float()
        return (err * m).sum() / m.sum().clamp_min(1.0)

    def forward(self, batch: dict):
        # the target follows the student as updated by the last optimiser step
        self.update_target()
        if self.objective == "trajectory":
            return self._trajectory_loss(batch)
        z0, noise, t, w = batch["latents"], batch["noise"], batch["timesteps"], batch["guidance"]
        s = (t - self.k).clamp_min(0)
        cond = self._student_cond(batch)
        zt = self.schedule.add_noise(z0, noise, t)
        pred = consistency_fn(self.schedule, zt, self.student(zt, t, guidance=w, **cond).float(), t)
        with torch.no_grad():
            x0, eps = self.schedule.to_x0_eps(zt, self._guided(zt, t, batch), t)
            zs = self.schedule.add_noise(x0, eps, s)         # the teacher's DDIM step t -> s
            target = consistency_fn(self.schedule, zs, self.target(zs, s, guidance=w, **cond).float(), s)
        loss = self._huber(pred, target, batch["frame_mask"])
        logs = {"loss": float(loss.detach()), "auto": float(batch["auto"].float().mean())}
        return self._with_adversarial(loss, pred, self._real_for(batch), batch, logs)

    def _judged(self, z: torch.Tensor) -> torch.Tensor:
        """What the discriminator sees of latents z: themselves, or the motion they decode to."""
        return z if self.decoder is None else self.decoder.decode(z / self.latent_scale)[0]

    def _with_adversarial(self, loss: torch.Tensor, pred: torch.Tensor, real: torch.Tensor | None, cond: dict,
                          logs: dict) -> tuple[torch.Tensor, dict]:
        """loss plus the adversarial terms: the student's, weighted so that its gradient on the clean
        estimates is lambda_adv times the consistency loss's (VQGAN's adaptive weight: a fixed weight
        would mean something else as the discriminator sharpens), and the discriminator's own. Each
        reaches only its player: the discriminator sees the estimates detached, the student sees the
        discriminator's parameters detached. real is already as the discriminator sees it (_judged)."""
        if self.disc is None:
            return loss, logs
        rows = cond.get("adversarial_rows")
        if rows is not None and not bool(rows.any()):
            return loss, {**logs, "judged_rows": 0.0}
        fm, pooled = cond["frame_mask"], cond["pooled"]
        judged = self._judged(pred)
        if fm is not None and judged.shape[1] != fm.shape[1]:
            fm = fm.repeat_interleave(judged.shape[1] // fm.shape[1], dim=1)
        mask = self.disc.patch_mask(judged, fm)
        if rows is not None:
            mask = mask & rows[:, None]
            logs["judged_rows"] = float(rows.float().mean())
        frozen = {k: v.detach() for k, v in self.disc.named_parameters()}
        g_adv = san_generator_loss(functional_call(self.disc, frozen, (judged, pooled, fm)), mask)
        g_rec = torch.autograd.grad(loss, pred, retain_graph=True)[0]
        if rows is not None:
            # the ratio on the judged rows alone: their push is lambda_adv times their own consistency gradient
            g_rec = g_rec[rows]
        g_fake = torch.autograd.grad(g_adv, pred, retain_graph=True)[0]
        weight = (self.lambda_adv * g_rec.norm() / g_fake.norm().clamp_min(1e-12)).detach()
        d_loss, d_logs = san_discriminator_loss(self.disc.san_logits(real.detach(), pooled, fm),
                                                self.disc.san_logits(judged.detach(), pooled, fm), mask)
        logs.update(d_logs, g_adv=float(g_adv.detach()), adv_weight=float(weight))
        return loss + weight * g_adv + d_loss, logs

    @torch.no_grad()
    def solve(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """The teacher's solution from batch["noise"] at t = T-1 with guidance: (the states at
        self.points (P, B, ...), the clean latent (B, ...))."""
        sched = self.schedule.sampler("dpm", timesteps=self.solve_timesteps)
        x = batch["noise"]
        states = {}
        for t in sched.timesteps:
            if int(t) in self.points:
                states[int(t)] = x
            tt = torch.full((x.shape[0],), int(t), dtype=torch.long, device=x.device)
            x = sched.step(self._guided(x, tt, batch), t, x).prev_sample
        return torch.stack([states[t] for t in self.points]), x

    @torch.no_grad()
    def sample_stochastic(self, batch: dict) -> torch.Tensor:
        """The teacher's clean latents for the batch's prompts, lengths and guidance scales from fresh
        noise by SDE-DPM-Solver++, guided as in solve: the livelier motions of the studio's sampler."""
        sched = self.schedule.sampler("dpm-sde", self.teacher_steps)
        # seeded by the batch (drawn from the run's generator, which a resume restores), so each solve's samples
        # are those an unbroken run would draw
        g = torch.Generator().manual_seed(int(batch["sde_seed"]))
        x = fresh_noise(batch["noise"], g)
        for t in sched.timesteps:
            tt = torch.full((x.shape[0],), int(t), dtype=torch.long, device=x.device)
            x = sched.step(self._guided(x, tt, batch), t, x, variance_noise=fresh_noise(x, g)).prev_sample
        return x

    @property
    def _real_is_data(self) -> bool:
        """The discriminator's real side is the batch's own latents, which a saved solve must then keep."""
        return self.disc is not None and self.adversarial_real == "data"

    @torch.no_grad()
    def _real_for(self, batch: dict) -> torch.Tensor | None:
        """The discriminator's real side for a batch, as it judges it (None without one). For a
        solve it is stored with the solve, so every replay reuses it rather than decoding it again."""
        if self.disc is None:
            return None
        return self._judged(batch["latents"] if self._real_is_data else self.sample_stochastic(batch))

    def _solved(self, batch: dict) -> dict:
        states, x0 = self.solve(batch)
        return {"states": states, "x0": x0, "real": self._real_for(batch), **{k: batch[k] for k in COND_KEYS},
                "adversarial_rows": batch.get("adversarial_rows"),
                "inputs": {k: batch[k] for k in SOLVE_INPUTS if batch.get(k) is not None
                           and (k != "latents" or self._real_is_data)}}

    def replay_state(self) -> dict[str, torch.Tensor]:
        """The replay buffer as what its solves were made from ("{solve}.{key}"), for a training state."""
        return {f"{i}.{k}": v for i, entry in enumerate(self._solves) for k, v in entry["inputs"].items()}

    def restore_replay(self, tensors: dict[str, torch.Tensor]) -> None:
        """A saved replay buffer: its solves are solved again at the next step, in that step's precision, as the
        unbroken run solved them."""
        solves: dict[int, dict] = {}
        for key, value in tensors.items():
            i, name = key.split(".", 1)
            solves.setdefault(int(i), {})[name] = value
        self._solves, self._unsolved = [], [solves[i] for i in sorted(solves)]

    def _trajectory_loss(self, batch: dict):
        if self._unsolved:
            device = batch["point"].device
            for inputs in self._unsolved:
                b = {k: inputs[k].to(device) if k in inputs else None for k in SOLVE_INPUTS}   # None: no mask
                B = b["noise"].shape[0]
                b.update(text=b["text2"][B:], text_mask=b["text_mask2"][B:], pooled=b["pooled2"][B:])
                self._solves.append(self._solved(b))
            self._unsolved = []
        if bool(batch["fresh"]) or not self._solves:
            entry = self._solved(batch)
            self._solves = (self._solves + [entry])[-self.replay_buffer:]
        else:
            entry = self._solves[min(int(float(batch["pick"]) * len(self._solves)), len(self._solves) - 1)]
        B = entry["x0"].shape[0]
        point = batch["point"][:B]
        zt = entry["states"][point, torch.arange(B, device=point.device)]
        t = torch.tensor(self.points, device=zt.device)[point]
        pred = consistency_fn(self.schedule, zt,
                              self.student(zt, t, guidance=entry["guidance"], **self._student_cond(entry)).float(), t)
        loss = self._huber(pred, entry["x0"], entry["frame_mask"])
        logs = {"loss": float(loss.detach()), "auto": float(entry["auto"].float().mean()),
                "solved": float(bool(batch["fresh"]))}
        return self._with_adversarial(loss, pred, entry["real"], entry, logs)


def _student_for(teacher: Denoiser, teacher_doc_config: dict, path: str, vae_checksums: set[str]) -> Denoiser:
    """The exported student at `path` as the start of a student for `teacher`: any width, but the
    same latents (one of `vae_checksums`), body parts, text features and diffusion."""
    student, doc, _ = load_consistency_student(path)
    s, t = student.config, teacher.config
    mismatched = [k for k in ("latent_dim", "parts", "text_dim", "cross_attention", "length_modes")
                  if getattr(s, k) != getattr(t, k)]
    mismatched += partner_mismatches(doc["config"], teacher_doc_config, vae_checksums)
    if mismatched:
        raise CheckpointError(f"student {path} does not fit the teacher: its {', '.join(mismatched)} differ")
    return student.train()


def _pad_tokens(tokens: torch.Tensor, mask: torch.Tensor, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    extra = length - tokens.shape[1]
    if extra <= 0:
        return tokens, mask
    return F.pad(tokens, (0, 0, 0, extra)), F.pad(mask, (0, extra), value=False)


class ConsistencyTask:
    kind = "consistency"

    def __init__(self, cfg: ConsistencyTrainConfig, show_progress: bool = True):
        validate(cfg)
        self.cfg = cfg
        root = Path(cfg.teacher)
        if not (root / "vae").is_dir() or not (root / "denoiser").is_dir():
            raise CheckpointError(f"teacher {root}: expected a model directory with vae/ and denoiser/")
        teacher, doc = load_denoiser(root / "denoiser")
        tcfg = doc["config"]
        if tcfg.get("vae_checksum") and tcfg["vae_checksum"] not in vae_latent_checksums(root / "vae"):
            raise CheckpointError(f"{root}: the denoiser was trained on a different VAE than {root / 'vae'}")
        if teacher.config.guidance_embedding:
            raise CheckpointError(f"{root / 'denoiser'} is a distilled student already; distil a CFG-trained denoiser")
        self.teacher_doc = doc
        self.vae_checksum = vae_latent_origin(root / "vae")
        # Batches are the denoiser's own (same latents, captions, class balance, length modes),
        # with every caption kept: the teacher's unconditional row is added here.
        teacher_training = doc.get("meta", {}).get("train_config", {})
        if not teacher_training and "average" in doc.get("meta", {}):
            raise CheckpointError(f"{root / 'denoiser'} averages denoisers trained with different configs (or with none "
                                  "recorded), so the posterior noise its batches were drawn with is unknown: distil "
                                  "from one of them")
        self.data = DenoiserTask(DenoiserTrainConfig(
            data=cfg.data, model=teacher.config, diffusion=from_dict(DiffusionConfig, tcfg["diffusion"]),
            vae=str(root / "vae"), text_encoder=tcfg["text_encoder"], text_dropout=0.0, optim=cfg.optim,
            auto_length_prob=cfg.auto_length_prob,
            posterior_noise=float(teacher_training.get("posterior_noise", 1.0))), show_progress=show_progress)
        if cfg.caption_crossover and self.data.text_encoder is None:
            raise ConfigError("caption_crossover encodes new captions, and a latent bundle (data.bundle) holds only "
                              "its own captions' features: distil from data.root")
        self.schedule = self.data.schedule
        self.grid = grid_timesteps(self.schedule)
        student = _student_for(teacher, tcfg, cfg.student, vae_latent_checksums(root / "vae")) if cfg.student else None
        disc, decoder = None, None
        if cfg.lambda_adv > 0:
            torch.manual_seed(cfg.run.seed)
            c = teacher.config
            if cfg.adversarial_space == "motion":
                # a copy: the data's VAE encodes batches where they are made, this one decodes on the model's device
                decoder = copy.deepcopy(self.data.vae)
                frame_dim = self.data.normalizer.dim
            else:
                frame_dim = c.parts * c.latent_dim
            disc = PromptDiscriminator(frame_dim, c.text_dim, cfg.discriminator)
        focus = None
        # the actions are judged, given rows, or choose the exported checkpoint
        if cfg.lambda_adv > 0 or cfg.focus_rows > 0 or cfg.select_from > 0:
            if cfg.focus_max_clips > 0:
                focus = self.data.rare_motions(cfg.focus_max_clips, "focus", "out of focus")
            elif cfg.focus_classes:                           # the config keeps the two exclusive
                focus = self.data.class_motions(cfg.focus_classes, "focus")
        self._focus_motions = focus if cfg.lambda_adv > 0 or cfg.focus_rows > 0 else None
        self._selection = _Selection(cfg, self.data.classes_of(focus)) if cfg.select_from else None
        # the motions focus_rows draws from, and how often each (the class balance among them)
        self._focus_index = self._focus_p = None
        if cfg.focus_rows:
            self._focus_index = np.flatnonzero(self._focus_motions)
            w = self.data.draw_weights
            self._focus_p = None if w is None else w[self._focus_index] / w[self._focus_index].sum()
        self.model = ConsistencyTraining(teacher, self.schedule, cfg.target_decay, cfg.huber_c, cfg.target,
                                         cfg.teacher_steps, cfg.replay_buffer, cfg.cfg_rescale, cfg.cfg_cutoff,
                                         student, disc, cfg.lambda_adv, decoder, self.data.latent_scale,
                                         cfg.adversarial_real)
        self._drawn = 0

    def _replayed(self, rng: np.random.Generator) -> dict | None:
        """For the trajectory target: a step that trains on a stored solve (None: solve afresh)."""
        if self.cfg.target != "trajectory":
            return None
        self._drawn += 1
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        B = self.cfg.optim.batch_size
        return {"point": torch.randint(0, len(self.model.points), (B,), generator=g),
                "pick": torch.rand((), generator=g), "fresh": torch.tensor((self._drawn - 1) % self.cfg.replay == 0)}

    def _focus_draw(self, rng: np.random.Generator) -> np.ndarray | None:
        """focus_rows motions of the actions in focus for a fresh batch's first rows (None: none asked)."""
        if self._focus_index is None:
            return None
        return self._focus_index[rng.choice(len(self._focus_index), size=self.cfg.focus_rows,
                                             p=self._focus_p)]

    def _cross_captions(self, b: dict, rng: np.random.Generator) -> None:
        """caption_crossover of b's rows take their caption crossed with another row's (with its text
        features); a discriminator of data no longer judges them, their capture not being what they say."""
        given = b["captions"]
        B = len(given)
        if B < 2:
            return
        captions = list(given)
        for r in np.flatnonzero(rng.random(B) < self.cfg.caption_crossover):
            other = int(rng.integers(B - 1))
            captions[r] = crossover(given[r], given[other + (other >= r)], rng)
        b["captions"] = captions
        b["text"], b["text_mask"], b["pooled"] = self.data.text_features(captions)
        if self.cfg.lambda_adv > 0 and self.cfg.adversarial_real == "data":
            kept = torch.tensor([c == g for c, g in zip(captions, given)])
            b["adversarial_rows"] = kept & b.get("adversarial_rows", torch.ones(B, dtype=torch.bool))

    def batch(self, rng: np.random.Generator) -> dict:
        replay = self._replayed(rng)
        if replay is not None and not bool(replay["fresh"]):
            return replay
        b = self.data.batch(rng, self._focus_draw(rng))
        if replay is not None:
            b.update(replay)
        if self._focus_motions is not None and self.cfg.lambda_adv > 0:
            b["adversarial_rows"] = torch.from_numpy(self._focus_motions[b["rows"].numpy()])
        if self.cfg.caption_crossover > 0:
            self._cross_captions(b, rng)
        B = b["latents"].shape[0]
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        b["timesteps"] = self.grid[torch.randint(0, len(self.grid), (B,), generator=g)]
        lo, hi = self.cfg.guidance_min, self.cfg.guidance_max
        b["guidance"] = lo + (hi - lo) * torch.rand(B, generator=g)
        if self.cfg.lambda_adv > 0 and self.cfg.adversarial_real == "teacher":
            b["sde_seed"] = torch.tensor(int(rng.integers(2 ** 62)))
        empty, empty_mask, empty_pooled = self.data.text.batch([""] * B)
        L = max(empty.shape[1], b["text"].shape[1])
        empty, empty_mask = _pad_tokens(empty, empty_mask, L)
        text, mask = _pad_tokens(b["text"], b["text_mask"], L)
        b["text"], b["text_mask"] = text, mask
        b["text2"], b["text_mask2"] = torch.cat((empty, text)), torch.cat((empty_mask, mask))
        b["pooled2"] = torch.cat((empty_pooled, b["pooled"]))
        return b

    def training_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """What a resumed run needs beyond weights, optimiser and generators to go on as an unbroken one would:
        where it is in the replay schedule, and the buffer of solves."""
        return self.model.replay_state(), {"drawn": self._drawn}

    def restore_training_state(self, tensors: dict[str, torch.Tensor], doc: dict) -> None:
        self._drawn = int(doc["drawn"])
        self.model.restore_replay(tensors)

    def loss(self, model: nn.Module, batch: dict):
        return model(batch)

    def load_weights(self, model: nn.Module, path: Path, continuing: bool = False) -> dict:
        """An exported student as both the student and its target network. Continuing takes only a
        student of this same teacher (e.g. one distilled on another machine); a new run (--init-from)
        may start from the student of an earlier teacher, e.g. the one this teacher was fine-tuned from."""
        student, doc, info = load_consistency_student(path)
        mine = self.teacher_doc["files"]["denoiser"]["sha256"]
        if continuing and info.get("teacher", {}).get("sha256") != mine:
            raise CheckpointError(f"{path} was distilled from another teacher than {self.cfg.teacher}'s denoiser; "
                                  "continue it with its own teacher, or distil afresh")
        load_state_strict(model.student, student.state_dict(), str(path))
        model.target.load_state_dict(model.student.state_dict())
        return doc.get("meta", {})

    def config_dict(self) -> dict:
        # the teacher's weights, not only its path: a run resumed after the teacher was replaced
        # (a newer snapshot in assets/model) must not go on distilling the old one
        return {**to_dict(self.cfg), "teacher_sha256": self.teacher_doc["files"]["denoiser"]["sha256"]}

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        teacher_meta = self.teacher_doc.get("meta", {})
        consistency = {"guidance": [self.cfg.guidance_min, self.cfg.guidance_max], "grid_steps": CONSISTENCY_GRID,
                       "cfg_rescale": self.cfg.cfg_rescale, "cfg_cutoff": self.cfg.cfg_cutoff,
                       "teacher": {"path": self.cfg.teacher, "step": teacher_meta.get("step"),
                                   "sha256": self.teacher_doc["files"]["denoiser"]["sha256"]}}
        if self._selection is not None:
            val = self._selection.judge(model.target, consistency, meta["step"], path)
            if val is None:
                return
            meta = {**meta, "val": val}
        save_denoiser(path, model.target, self.schedule.config, self.data.text_spec, self.data.canvas,
                      self.vae_checksum, meta={**meta, "consistency": consistency, "train_config": to_dict(self.cfg),
                                               "latent_scale": self.data.latent_scale})


class _Selection:
    """select_from: which checkpoints' students are exported. Each one from select_from on is judged on the
    actions in focus, on motions from their training captions (validate_actions), and exported only where it
    scores above the one model/ holds (from this same config)."""

    def __init__(self, cfg: ConsistencyTrainConfig, contents: list[str]):
        from ..eval.fidelity import fidelity_classes
        known = {c.key for c in fidelity_classes(None)}
        if not set(contents) <= known:
            raise ConfigError(f"select_from judges the actions in focus with the fidelity checks, which have no "
                              f"class for {sorted(set(contents) - known)}; name others in focus_classes")
        self.cfg, self.contents, self.pipe = cfg, contents, None

    def judge(self, student: Denoiser, consistency: dict, step: int, path: Path) -> dict | None:
        """The validation of `student` at `step` (logged to val.jsonl beside `path`), or None where it is not
        to be exported: before select_from, or not better than the export at `path`."""
        from ..eval.fidelity import validate_actions
        from ..eval.selection import best_score, log_validation
        from ..pipeline import load_pipeline
        if step < self.cfg.select_from:
            return None
        device, started = next(student.parameters()).device, time.time()
        # the run draws the same numbers whether or not it judges its checkpoints (loading the pipeline
        # initialises modules), so a judged run trains as an unjudged one and resumes as it would have gone on
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            if self.pipe is None:  # the teacher's pipeline without its own student, which may be an older teacher's
                self.pipe = load_pipeline(self.cfg.teacher, device=device, student=False)
            self.pipe.use_student(copy.deepcopy(student), consistency)
            val = validate_actions(self.pipe, self.cfg.data.root, self.contents, captions=self.cfg.select_captions)
            self.pipe.use_student(None)
        log_validation(path.parent, {"step": step, "score": val["score"], "passed": val["passed"],
                                     "margin": val["margin"], "motions": sum(v["motions"] for v in val["classes"].values()),
                                     "seconds": round(time.time() - started, 1),
                                     "classes": {k: round(v["margin"], 4) for k, v in val["classes"].items()}})
        return val if val["score"] > best_score(path, "denoiser", self.cfg) else None
