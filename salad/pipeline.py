"""The one public entry point: load_pipeline() -> Pipeline with generate / edit / control.

Data flows one way: prompt -> text encoder -> denoiser (with optional attention
controllers) -> diffusion sampler -> VAE decoder -> features -> joints.
"""
from __future__ import annotations

import math
import os
from contextlib import ExitStack, nullcontext
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .allocator import keep_large_blocks
from .checkpoint import CheckpointError
from .files import REPO_ROOT
from .diffusion.guidance import (DEFAULT_GRADIENT_STEPS, DEFAULT_REFINE_STEPS, STUDENT_REFINE_STEPS,
                                 default_repeats, guided_consistency_sample, guided_sample, planted_feet_loss,
                                 position_loss, refine)
from .diffusion.consistency import consistency_sample
from .diffusion.sampling import sample
from .diffusion.schedule import CONSISTENCY_GRID, SAMPLERS, DiffusionConfig, NoiseSchedule
from .editing.build import build_edit, step_follower
from .editing.real import edit_real
from .editing.spec import DEFAULT_SELF_INJECT, EditResult, EditSpec
from .editing.replay import SourceRecorder, SourceRun, SourceRuns
from .editing.store import AttentionStore, RowAddressed
from .config import from_dict
from .models.denoiser import Denoiser
from .models.io import (load_consistency_student, load_denoiser, load_vae, partner_mismatches,
                        vae_latent_checksums)
from .models.text import TextEncoder, load_text_encoder
from .models.vae import MotionVAE
from .models.vocabulary import PromptCheck
from .precision import BF16_MIN_ROWS, bf16_supported, resolve_device
from .progress import Progress, continued
from .motion.cleanup import clean_motion
from .motion.footlock import planted_mask
from .motion.control import control_errors, make_signal
from .motion.motion import Motion
from .motion.representation import CONTACT_SLICE, FPS, MIN_AUTO_FRAMES, Normalizer, features_to_joints

EMBEDDED_MODEL = REPO_ROOT / "assets" / "model"
MAX_PROMPT_CHARS = 300
# torch seeds a generator with a 64-bit integer, and the step noise takes seed + 1
MAX_SEED = 2**63 - 2
ACTIVATION_THRESHOLD = 0.5
# Auto length is the model's own (its activation channel, MoLA) held within this factor of the length
# prior (the training motions of the captions nearest the prompt); a motion that ends outside the band
# is sampled again at the band's edge. The activation alone gets badly learnt actions grossly wrong
# (a backward walk 1.4 s against 8.0 real), the prior alone mixes manners (slower styles' raises,
# plain walks for an exhausted one). Chosen on the validation split (72 captions of 17 actions, one
# each; teacher): within ±35% of their own motion's length 0.83 of them (activation), 0.82 (prior),
# 0.85 (geometric mean), 0.88 with a band of 1.25 or 1.5; action medians within ±35%: 11, 16, 14,
# 14 and 13 of 17. It resamples about a third of the motions. Checked again when the prior moved to the
# caption index (session 35; one caption of each of the 79 validation action-style groups, equal-draw
# teacher): within +-35% with bands of 1.1, 1.25, 1.5, 2 and none (the prior alone): 0.91, 0.91, 0.90, 0.86
# and 0.86 (the sample's prior with 1.25: 0.82); action medians 14, 14, 14, 11 and 13 of 17 (sample: 13).
AUTO_LENGTH_BAND = 1.25
# An auto length is laid down early: after 30% of the steps the clean estimate's activation ends on the same
# side of the band as the finished motion's (session 40, teacher, DDIM-50, one validation caption per
# action-style group and the studio bench's three prompts, 2 seeds: 162 of 164 at step 15, 159 at step 10, all
# from step 20; the two at step 15 ended on the band's lower edge, so held there they keep their length). So a
# sampling whose estimate has left the band by then stops and samples again at the edge instead of finishing
# a motion that would be thrown away (38 of the 164). The finished motion is still checked.
LENGTH_SETTLED = 0.3
# Generated latents can go through the VAE once more before the last decode: decoded, encoded to the
# posterior mean, decoded again (set_projections). It pulls a motion towards where real ones lie and
# smooths it; it was the default from session 27 (a bow's jerk 11.0 -> 6.0 m/s³, real 4.1; the plain walk's
# still feet 0.79 -> 0.90) until the planted-feet refinement below took over the feet. Session 34, the
# equal-draw teacher and its student, held-out sets a / b, 3 seeds, raw classes, without / with it:
# - teacher: 24 / 23 against 23 / 23, paraphrases read as their action 93% / 88% against 92% / 86%, kick
#   0.64 / 0.71 m against 0.49 / 0.55 (real 1.00), walks' still feet 1.00 either way; T2M FID 3.65e-3 (dpm-20);
# - student: 23 / 21 against 24 / 23 (its bow's jerk 11.8 against 6.9 m/s³, rule 10.3), paraphrases 88% / 85%
#   against 84% / 82%, T2M FID 4.41e-3 against 6.10e-3: with it the student would be 1.67x the teacher's FID,
#   past the 1.5x bound, and smoother than the real clips in most standing actions (byebye 5.3 m/s³, real 13.8).
LATENT_PROJECTIONS = 0
# Then the feet the decoder marks as planted are made to stand still through the decoder itself: the
# latent is refined by L-BFGS within this many loss evaluations (guidance.planted_feet_loss), so the legs
# and the root move with the feet as the decoder would move them (the foot lock afterwards has little left
# to do). The denoiser alone lets planted feet slide: its error builds up over the sampling steps
# (assets/RESULTS.md, *Feet*). 0 turns it off. Motions whose planted feet already move slower than
# STILL_FEET_MPS (rms) are left as they are: standing actions cost nothing.
FOOT_REFINE_EVALUATIONS = 20
STILL_FEET_MPS = 0.1
# Guided control refines its planted feet too, with its targets' loss (guidance.position_loss) at this
# weight beside the feet's: on the student's path benchmark (32 test paths) foot skating went from 0.100 to
# 0.021 (real 0.025) and the mean path error from 13 to 10 mm; at weight 1 the targets held the legs
# (skating 0.042), without them one path strayed over 20 cm.
CONTROL_FEET_TARGETS = 0.1
# dpm-sde at 25 steps: the fidelity table of ancestral DDIM-50 (six seeds pooled, sets a / b: 26 / 25 classes raw
# either way) in half the forwards; at 20 steps it lost set a's punch (session 51, assets/RESULTS.md, Limitations).
DEFAULT_STEPS = {"ddim": 50, "dpm": 50, "dpm-sde": 25, "consistency": 4}
# Recorded source runs kept for edits to replay (salad.editing.replay): the teacher's record of a 9.8 s
# canvas at 50 steps is about 90 MB in float32. Two cover a generated motion and the edit source before it.
SOURCE_RUNS = 2
# What Pipeline.compile can hand to torch.compile. On a 2-core AVX2 CPU (session 48) it took a 4-step generation
# from 73-85 to 62-68 ms and DDIM-50 from 0.88-0.99 to 0.71-0.75 s, for 16-69 s of compiling at the first call;
# off by default, as the studio's samplings mostly run observed (eager) and one-off commands would not repay it.
COMPILABLE = ("denoiser", "student", "decoder")
# what a student can be measured fit for (meta.consistency.default_for, Pipeline.student_preferred)
STUDENT_USES = ("text", "edit", "control")
# The teacher's sampling: DDIM with fresh noise at every step (eta = 1) and guidance rescaled
# halfway to the conditional prediction's scale. The deterministic DDIM (eta = 0) blurs gait
# phases: on the embedded model its walks kept a foot still in 0.62 of their frames against
# 0.71 at eta = 1 and 0.72-0.76 with the rescale (model card, *Ancestral sampling*; the cutoff below: *Guidance cutoff*).
DDIM_ETA = 1.0
CFG_RESCALE = 0.7
# Guidance stops below t = 300 of 1000 (the last 15 of 50 DDIM steps take the conditional prediction
# alone): the action is settled by then, and guidance there only made the feet slide.
CFG_CUTOFF = 0.3



class _LengthLeftBand(Exception):
    """A length watch's stop after `steps` reported steps: sample again at `frames`, the band's edge."""

    def __init__(self, frames: int, steps: int):
        super().__init__(frames)
        self.frames, self.steps = frames, steps


class Pipeline:
    def __init__(self, vae: MotionVAE, normalizer: Normalizer, latent_scale: float, denoiser: Denoiser,
                 text_encoder: TextEncoder, schedule: NoiseSchedule, canvas_frames: int, bf16: bool = True,
                 bf16_min_rows: int = BF16_MIN_ROWS, source: str = "", prompt_check: PromptCheck | None = None,
                 device: str | torch.device = "auto",
                 student: Denoiser | None = None, student_info: dict | None = None):
        self.device = resolve_device(device)
        if self.device.type == "cpu":
            keep_large_blocks()
        self.vae, self.normalizer, self.latent_scale = vae.eval().to(self.device), normalizer, latent_scale
        self.denoiser, self.schedule = denoiser.eval().to(self.device), schedule
        self.text_encoder = text_encoder.to(self.device)
        self.canvas_frames = canvas_frames
        self.bf16 = bf16 and bf16_supported(self.device)
        if not isinstance(bf16_min_rows, int) or isinstance(bf16_min_rows, bool) or bf16_min_rows < 1:
            raise ValueError(f"bf16_min_rows must be a positive integer, got {bf16_min_rows!r}")
        self.bf16_min_rows = bf16_min_rows
        self.source = source
        self.prompt_check = prompt_check
        # inference only: guided control and null-text inversion differentiate through these
        # modules, and weight gradients nobody reads were a third of a decoder backward
        for m in (self.vae, self.denoiser, self.text_encoder):
            m.requires_grad_(False)
        self.ddim_eta, self.cfg_rescale, self.cfg_cutoff = DDIM_ETA, CFG_RESCALE, CFG_CUTOFF
        self.projections = LATENT_PROJECTIONS
        self.foot_refine = FOOT_REFINE_EVALUATIONS
        self.compiled: dict[str, Callable] = {}
        self.source_runs = SourceRuns(SOURCE_RUNS)
        self.use_student(student, student_info)

    def use_student(self, student: Denoiser | None, info: dict | None = None) -> None:
        """The consistency-distilled student that sampler="consistency" runs (None: none), e.g. the model's own
        or a checkpoint being chosen during distillation; info: the guidance range it learnt and the teacher it
        was distilled from (its checkpoint's meta.consistency)."""
        self.student = None if student is None else student.eval().requires_grad_(False).to(self.device)
        self.student_info = info or {}
        self.compiled.pop("student", None)
        self.source_runs.clear()        # an edit must not replay another network's sampling

    def compile(self, parts: tuple[str, ...] = COMPILABLE) -> None:
        """Run `parts` (of COMPILABLE) through torch.compile, with dynamic shapes, from their next call on:
        the denoiser and the student wherever no attention controller observes them and no gradient is
        taken (sampling for generate, control and the benchmarks; edits and the attention explorer stay
        eager), and the VAE's decoder for the decode after sampling. Each compiles at its first call and may
        compile again for a new batch size (on a 2-core CPU 16-69 s in all); the results match the eager
        modules' to float rounding. It needs a C compiler (inductor's CPU code)."""
        unknown = [p for p in parts if p not in COMPILABLE]
        if unknown:
            raise ValueError(f"cannot compile {', '.join(map(repr, unknown))}; choose from {', '.join(COMPILABLE)}")
        modules = {"denoiser": self.denoiser, "student": self.student, "decoder": self.vae.decode}
        for name in parts:
            if modules[name] is not None and name not in self.compiled:
                self.compiled[name] = torch.compile(modules[name], dynamic=True)

    def _network_call(self, name: str) -> Callable:
        """The denoiser or the student as it should run now: compiled (compile()) unless an attention
        controller observes it or a gradient flows through it."""
        net = self.student if name == "student" else self.denoiser
        fast = self.compiled.get(name)
        if fast is None or torch.is_grad_enabled() or any(a.controller is not None for a in net.attentions()):
            return net
        return fast

    def set_sampling(self, ddim_eta: float | None = None, cfg_rescale: float | None = None,
                     cfg_cutoff: float | None = None) -> None:
        """The teacher's sampler settings (None keeps one): ddim_eta in [0, 1], the fresh noise
        DDIM adds at each step (0: the paper's deterministic DDIM); cfg_rescale in [0, 1], how far
        guided predictions are pulled to the conditional one's scale (0: plain guidance);
        cfg_cutoff in [0, 1), the share of the noise levels, from the clean end, sampled without
        guidance (0: guidance at every step)."""
        for name, value, top in (("ddim_eta", ddim_eta, 1.0), ("cfg_rescale", cfg_rescale, 1.0),
                                 ("cfg_cutoff", cfg_cutoff, 0.99)):
            if value is not None and not (isinstance(value, (int, float)) and 0.0 <= value <= top):
                raise ValueError(f"{name} must be a number in [0, {top:g}], got {value!r}")
        if ddim_eta is not None:
            self.ddim_eta = float(ddim_eta)
        if cfg_rescale is not None:
            self.cfg_rescale = float(cfg_rescale)
        if cfg_cutoff is not None:
            self.cfg_cutoff = float(cfg_cutoff)

    def set_projections(self, projections: int) -> None:
        """How many times generated latents go through the VAE (decode, encoder mean) before the
        last decode: 0 decodes the sampler's latents as they are (LATENT_PROJECTIONS)."""
        if not isinstance(projections, int) or isinstance(projections, bool) or not 0 <= projections <= 8:
            raise ValueError(f"projections must be an integer in 0..8, got {projections!r}")
        self.projections = projections

    def set_foot_refine(self, evaluations: int) -> None:
        """How many loss evaluations the planted-feet refinement of generated motions may take
        (FOOT_REFINE_EVALUATIONS; 0: none)."""
        if not isinstance(evaluations, int) or isinstance(evaluations, bool) or not 0 <= evaluations <= 500:
            raise ValueError(f"foot refinement evaluations must be an integer in 0..500, got {evaluations!r}")
        self.foot_refine = evaluations

    def sampler_settings(self, sampler: str) -> dict:
        """What a report should record of the sampling settings for `sampler` (the teacher's, and the
        latent projections every sampler's motions go through), and the precision the model ran in."""
        guidance = {"cfg_rescale": self.cfg_rescale, "cfg_cutoff": self.cfg_cutoff}
        teacher = {"ddim": {"ddim_eta": self.ddim_eta, **guidance}, "dpm": guidance, "dpm-sde": guidance}.get(sampler, {})
        return {**teacher, "projections": self.projections, "foot_refine": self.foot_refine,
                "precision": self.precision}

    @property
    def precision(self) -> str:
        """How the networks compute, in words (reports record it)."""
        if not self.bf16:
            return "fp32"
        return "bf16 autocast" if self.bf16_min_rows <= 1 else f"bf16 autocast from {self.bf16_min_rows} rows a forward"

    # ------------------------------------------------------------ validation
    @property
    def max_seconds(self) -> float:
        return self.canvas_frames / FPS

    def check_prompt(self, prompt) -> str:
        if not isinstance(prompt, str):
            raise ValueError(f"prompt must be a string, got {type(prompt).__name__}")
        p = " ".join(prompt.split())
        if not p:
            raise ValueError("prompt is empty: describe the motion, e.g. 'a person walks forward'")
        if len(p) > MAX_PROMPT_CHARS:
            raise ValueError(f"prompt is {len(p)} characters long; the limit is {MAX_PROMPT_CHARS}")
        return p

    @staticmethod
    def check_seed(seed) -> int:
        # a negative seed would be taken silently as another one (-1 means "random" in some tools: not here)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
            raise ValueError(f"seed must be an integer in 0..{MAX_SEED}, got {seed!r}")
        return int(seed)

    def prompt_warnings(self, prompt: str) -> list[str]:
        """What a user should know about how the model will take `prompt` (an action or words it
        was not trained on, another language); empty when all is well or the model ships no
        vocabulary. Every generated motion carries these as `motion.warnings`."""
        return self.prompt_check.warnings(self.check_prompt(prompt)) if self.prompt_check else []

    def frames_for(self, seconds, prompt: str | None = None) -> int | None:
        """Requested duration -> frame count (a multiple of 4), or None where the model ends the motion
        itself (its activation channel, MoLA): seconds=None or "auto" (then held within AUTO_LENGTH_BAND
        of the length prior, see auto_length_band) and "model" (the activation alone). seconds="prior":
        the length the training data gives motions like `prompt` (PromptCheck.length_prior), for models
        that ship a vocabulary with lengths."""
        keyword = _length_keyword(seconds)
        if keyword in ("auto", "model"):
            return None
        if keyword == "prior":
            prior = self.prompt_check.length_prior(prompt) if self.prompt_check and prompt else None
            if prior is None:
                raise ValueError("seconds='prior' needs a prompt and a model whose vocabulary keeps motion lengths "
                                 "(salad data vocabulary writes one); use a number or 'auto'")
            return self._frames_near(prior)
        try:
            s = float(seconds)
        except (TypeError, ValueError):
            raise ValueError(f"seconds must be a number, 'auto', 'model' or 'prior', got {seconds!r}") from None
        lo, hi = MIN_AUTO_FRAMES / FPS, self.max_seconds
        if not math.isfinite(s) or not lo <= s <= hi:
            raise ValueError(f"seconds must be between {lo:g} and {hi:g}, got {seconds!r}")
        return self._frames_near(s)

    @staticmethod
    def length_source(seconds) -> str:
        """How frames_for(seconds) chose a length that it did choose: "requested" or "prior"."""
        return "prior" if _length_keyword(seconds) == "prior" else "requested"

    def _frames_near(self, seconds: float) -> int:
        return max(MIN_AUTO_FRAMES, min(self.canvas_frames, int(round(seconds * FPS / 4)) * 4))

    def auto_length_band(self, prompt: str) -> tuple[int, int] | None:
        """(shortest, longest) frame count an auto-length motion for `prompt` may have: the length prior
        divided and multiplied by AUTO_LENGTH_BAND; None where the model ships no lengths to hold to."""
        prior = self.prompt_check.length_prior(prompt) if self.prompt_check and prompt else None
        if prior is None:
            return None
        return self._frames_near(prior / AUTO_LENGTH_BAND), self._frames_near(prior * AUTO_LENGTH_BAND)

    def _band_for(self, seconds, prompt: str) -> tuple[int, int] | None:
        """The band an auto length must keep to, for lengths chosen by seconds="auto" (None otherwise)."""
        return self.auto_length_band(prompt) if _length_keyword(seconds) == "auto" else None

    @staticmethod
    def _held_length(band: tuple[int, int] | None, frames: int) -> int | None:
        """The frame count to sample again at when the auto length `frames` left `band` (None: keep it)."""
        if band is None or band[0] <= frames <= band[1]:
            return None
        return min(max(frames, band[0]), band[1])

    def _length_watch(self, band: tuple[int, int] | None, steps: int, sampler: str):
        """A denoise watch that stops an auto-length sampling (raising _LengthLeftBand) when its first row's
        clean estimate after LENGTH_SETTLED of the steps ends outside `band`; None where there is no band, or
        too few steps for an early look to save any (the consistency sampler's 1-4)."""
        check = math.ceil(steps * LENGTH_SETTLED)
        if band is None or sampler == "consistency" or check >= steps:
            return None

        def watch(i: int, x0: torch.Tensor) -> None:
            if i != check:
                return
            with torch.no_grad():
                _, act_logits = self.vae.decode(x0[:1] / self.latent_scale)
            if act_logits is None:
                return
            held = self._held_length(band, end_of_motion(torch.sigmoid(act_logits[0]).cpu().numpy()))
            if held is not None:
                raise _LengthLeftBand(held, steps=i - 1)

        return watch

    def check_sampling(self, steps, cfg, sampler, batch=1) -> tuple[int, float, str, int]:
        """Checked (steps, cfg, sampler, batch); steps=None is the sampler's default
        (DEFAULT_STEPS)."""
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
        if steps is None:
            steps = DEFAULT_STEPS[sampler]
        top = CONSISTENCY_GRID if sampler == "consistency" else 1000
        if not isinstance(steps, (int, np.integer)) or not 1 <= steps <= top:
            raise ValueError(f"steps must be an integer in 1..{top} for the {sampler} sampler, got {steps!r}")
        if not isinstance(cfg, (int, float)) or not math.isfinite(cfg) or not 0 <= cfg <= 30:
            raise ValueError(f"cfg must be a number in 0..30, got {cfg!r}")
        if sampler == "consistency":
            if self.student is None:
                raise ValueError("this model has no consistency student (a consistency/ checkpoint next to denoiser/):"
                                 " distil one with `salad train consistency`, or use the ddim or dpm sampler")
            lo, hi = self.guidance_range
            if not lo <= cfg <= hi:
                raise ValueError(f"the consistency student was distilled for cfg {lo:g}..{hi:g}, got {cfg!r}; "
                                 "use the ddim or dpm sampler for other scales")
        if not isinstance(batch, (int, np.integer)) or not 1 <= batch <= 64:
            raise ValueError(f"batch must be an integer in 1..64, got {batch!r}")
        return int(steps), float(cfg), sampler, int(batch)

    @property
    def guidance_range(self) -> tuple[float, float]:
        lo, hi = self.student_info.get("guidance", (0.0, 30.0))
        return float(lo), float(hi)

    def student_preferred(self, use: str) -> bool:
        """Whether the student was measured to meet its quality bounds against the teacher for `use`
        ("text": motions from text; "edit": the four edit modes on generated and real motion; "control":
        guided control), as its checkpoint records in meta.consistency.default_for. A student without that
        record (a fresh distillation) is preferred nowhere until someone has measured it."""
        if use not in STUDENT_USES:
            raise ValueError(f"use must be one of {', '.join(STUDENT_USES)}, got {use!r}")
        return self.student is not None and use in self.student_info.get("default_for", ())

    # ------------------------------------------------------------ building blocks
    def autocast(self, rows: int | None = None):
        """bf16 autocast where the pipeline runs bf16 and a forward of `rows` rows (None: any) reaches
        bf16_min_rows; else nothing."""
        on = self.bf16 and (rows is None or rows >= self.bf16_min_rows)
        return torch.autocast(self.device.type, dtype=torch.bfloat16) if on else nullcontext()

    def encode_text(self, prompts: list[str]):
        """Token features for `prompts`, padded together (cached per prompt by the encoder)."""
        return self.text_encoder.encode(prompts)

    def noise(self, batch: int, frames: int, seed: int) -> torch.Tensor:
        # drawn on the CPU whatever the device: a seed starts from the same noise on every machine
        g = torch.Generator().manual_seed(int(seed))
        c = self.denoiser.config
        return torch.randn(batch, frames // 4, c.parts, c.latent_dim, generator=g).to(self.device)

    def model_fn(self, text, auto: bool, frame_mask: torch.Tensor | None = None):
        """The denoiser as the sampler sees it: rows are [unconditional..., conditional...].
        frame_mask (B, T) marks real latent frames when motions of several lengths share a batch."""
        rows_mask = None if frame_mask is None else torch.cat((frame_mask, frame_mask))

        def run(x: torch.Tensor, t: torch.Tensor, rows: slice, mask: torch.Tensor | None) -> torch.Tensor:
            with self.autocast(x.shape[0]):
                flags = torch.full((x.shape[0],), auto, device=x.device)
                return self._network_call("denoiser")(
                    x, t, text.tokens[rows], text.mask[rows], mask,
                    pooled_text=None if text.pooled is None else text.pooled[rows], auto_length=flags).float()

        def fn(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return run(x, t, slice(None), rows_mask)

        # Unguided steps need the prompts' rows alone. An attention controller (an edit, the explorer's
        # store) addresses rows of the full [unconditional, conditional] layout, so it is told that the
        # unconditional rows are missing, or, where it reads them, the steps keep every row.
        controllers = list({id(a.controller): a.controller for a in self.denoiser.attentions()
                            if a.controller is not None}.values())
        uncond = text.tokens.shape[0] // 2

        def conditional(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            with ExitStack() as stack:
                for c in controllers:
                    stack.enter_context(c.leading_rows_dropped(x.shape[0]))
                return run(x, t, slice(x.shape[0], None), frame_mask)

        if all(isinstance(c, RowAddressed) and c.lowest_row() >= uncond for c in controllers):
            fn.conditional = conditional
        return fn

    def network(self, sampler: str) -> Denoiser:
        """The network a sampler runs: the distilled student for "consistency", else the denoiser."""
        return self.student if sampler == "consistency" else self.denoiser

    def sampler_text(self, prompts: list[str], sampler: str):
        """The encoded rows a sampler's network sees: the teacher's CFG layout [""..., prompts...],
        or the prompts alone for the student, whose guidance is a condition."""
        return self.encode_text(list(prompts) if sampler == "consistency" else [""] * len(prompts) + list(prompts))

    @staticmethod
    def conditional_rows(batch: int, sampler: str) -> slice:
        """Rows of the prompts themselves in sampler_text's layout."""
        return slice(0, batch) if sampler == "consistency" else slice(batch, 2 * batch)

    def student_fn(self, text, auto: bool, cfg: float, frame_mask: torch.Tensor | None = None):
        """The student as the consistency loop sees it: one row per motion, the guidance scale as input."""
        def fn(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            with self.autocast(x.shape[0]):
                flags = torch.full((x.shape[0],), auto, device=x.device)
                w = torch.full((x.shape[0],), float(cfg), device=x.device)
                return self._network_call("student")(x, t, text.tokens, text.mask, frame_mask,
                                                     pooled_text=text.pooled, auto_length=flags, guidance=w).float()
        return fn

    def source_key(self, prompt: str, frames: int | None, seed: int, steps: int, cfg: float, sampler: str) -> tuple:
        """What decides a source branch's sampling (frames None: automatic length), so that a recorded
        run is replayed only where sampling again would compute the same."""
        return (prompt, frames, int(seed), steps, cfg, sampler, self.ddim_eta, self.cfg_rescale, self.cfg_cutoff,
                self.precision)

    @staticmethod
    def records(sampler: str) -> bool:
        """Whether runs of `sampler` are recorded for edits to replay: the teacher's, whose CFG layout
        lets the edited branch run alone (the student's edits take 4 forwards of 2 rows already)."""
        return sampler != "consistency"

    def denoise(self, text, noise: torch.Tensor, sampler: str, steps: int, cfg: float, auto: bool,
                seed: int | list[int] = 0, frame_mask: torch.Tensor | None = None, shared_noise: bool = False,
                on_step=None, blend=None, start: int = 0, watch=None) -> torch.Tensor:
        """Clean latents from `noise` with `text` in sampler_text's layout. The consistency sampler
        and DDIM with ddim_eta > 0 draw fresh noise at each step seeded by `seed` (shared by all
        rows with shared_noise; a list gives each row its own seed, as if it were sampled alone).
        blend(x) changes the latents after each step (the consistency sampler: its clean estimates).
        start > 0 (ddim and consistency) begins that many steps down: `noise` is then a latent noised to
        that step's timestep (SDEdit). watch(i, x0) sees each step's clean estimate (ddim and dpm: sample's
        watch; the consistency sampler ignores it)."""
        if isinstance(seed, (list, tuple)):
            g = [torch.Generator().manual_seed(int(s) + 1) for s in seed]
        else:
            g = torch.Generator().manual_seed(int(seed) + 1)
        if sampler == "consistency":
            return consistency_sample(self.student_fn(text, auto, cfg, frame_mask), noise, self.schedule, steps,
                                      generator=g, shared_noise=shared_noise, on_step=on_step,
                                      on_clean=None if blend is None else (lambda t, x0: blend(x0)), start=start)
        return sample(self.model_fn(text, auto=auto, frame_mask=frame_mask), noise, self.schedule, sampler=sampler,
                      steps=steps, cfg_scale=cfg, on_step=on_step, blend=blend, generator=g, shared_noise=shared_noise,
                      eta=self.ddim_eta if sampler == "ddim" else 0.0, cfg_rescale=self.cfg_rescale,
                      cfg_cutoff=self.cfg_cutoff, start=start, watch=watch)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor, frames: int | None, texts: list[str], seed: int,
               foot_lock: bool = True, length: str = "requested", project: bool = True,
               feet: str = "refine", feet_also: Callable[[torch.Tensor], torch.Tensor] | None = None
               ) -> list[Motion]:
        """Latents -> motions; with frames=None each motion ends where its activation drops.
        project: the motion, cut to its length, goes through the VAE self.projections times first
        (LATENT_PROJECTIONS; info["projections"] says how many). feet: "refine" runs the planted-feet
        refinement (plant_feet; nothing when self.foot_refine is 0), "defer" leaves it to each motion's
        pending_refinement (refine_feet), "keep" leaves the feet as decoded; feet_also(z) (z in the VAE's
        units, one row) joins the refinement's loss (guided control: its targets). foot_lock cleans the joints
        (salad.motion.cleanup: bones held at constant length, the feet the decoder marks as planted
        pinned): the joints carry the clean-up, the features stay the decoder's output,
        info["foot_lock"] says what moved. info["length"] says where the length came
        from: "requested", "prior" (the training data's), "model" (the activation's, auto length) or
        "held" (an auto length sampled again at the edge of the prior's band)."""
        if feet not in ("refine", "defer", "keep"):
            raise ValueError(f"feet must be refine, defer or keep, got {feet!r}")
        decoded, act_logits = self.compiled.get("decoder", self.vae.decode)(latents / self.latent_scale)
        passes = self.projections if project else 0
        out = []
        for b in range(latents.shape[0]):
            n = decoded.shape[1]
            if frames is None and act_logits is not None:
                n = end_of_motion(torch.sigmoid(act_logits[b]).cpu().numpy())
            f = decoded[b:b + 1, :n]
            z = latents[b:b + 1, : n // 4] / self.latent_scale
            for _ in range(passes):
                z = self.vae.encode(f)[0]
                f, _ = self.vae.decode(z)
            info = {"length": "model" if frames is None else length, "projections": passes}
            deferred = self.foot_refine and feet == "defer"
            if self.foot_refine and feet == "refine":
                f, info["foot_refine"] = self.plant_feet(z, f, feet_also)
            f_decoded = f.detach().clone() if deferred else None
            f = self.normalizer.denormalize(f[0].float()).cpu().numpy()
            joints = features_to_joints(f)
            if foot_lock:
                joints, info["foot_lock"] = clean_motion(joints, f)
            m = Motion(joints=joints, features=f, text=texts[b], seed=seed, info=info,
                       warnings=self.prompt_warnings(texts[b]) if texts[b] else [])
            if deferred:
                m.pending_refinement = partial(self._refined, m, z.detach().clone(), f_decoded, feet_also)
            out.append(m)
        return out

    @staticmethod
    def refine_feet(motion: Motion) -> Motion:
        """A motion generated, edited or guided with foot_refine=False -> the motion that call would have
        returned with it: its planted feet refined through the decoder (plant_feet), the foot lock applied
        again where the motion had it. A motion with nothing pending (already refined, or from a path that
        decodes without the refinement) comes back as it is."""
        return motion if motion.pending_refinement is None else motion.pending_refinement()

    @torch.no_grad()
    def _refined(self, motion: Motion, z: torch.Tensor, decoded: torch.Tensor, also=None) -> Motion:
        """The pending refinement of `motion`, decoded from latent z (VAE units) as `decoded` (normalised
        features), with also() in its loss. The decoder's own tensor, not motion.features normalised again:
        the refinement's line search turns that round trip's rounding into millimetres."""
        if not self.foot_refine:
            return replace(motion, pending_refinement=None)
        refined, report = self.plant_feet(z.to(self.device), decoded.to(self.device), also)
        features = self.normalizer.denormalize(refined[0].float()).cpu().numpy()
        joints = features_to_joints(features)
        info = dict(motion.info, foot_refine=report)
        if "foot_lock" in motion.info:
            joints, info["foot_lock"] = clean_motion(joints, features)
        return replace(motion, joints=joints, features=features, info=info, pending_refinement=None)

    def plant_feet(self, z: torch.Tensor, features: torch.Tensor,
                   also: Callable[[torch.Tensor], torch.Tensor] | None = None) -> tuple[torch.Tensor, dict]:
        """One generated motion's latent z (1, T/4, 7, D), in the VAE's units, and the normalised
        features decoded from it (1, T, 263) -> the features decoded from z refined so that the feet
        the decoder marks as planted stand still (FOOT_REFINE_EVALUATIONS), also(z) added to the
        loss where given, and a report: the planted feet's rms speed before and after, m/s, and the
        loss evaluations allowed (0 where the feet already stood, under STILL_FEET_MPS)."""
        def joints_of(latent: torch.Tensor) -> torch.Tensor:
            return features_to_joints(self.normalizer.denormalize(self.vae.decode(latent)[0].float()))

        phys = self.normalizer.denormalize(features[0].float())
        joints = features_to_joints(phys)
        mask = planted_mask(joints.cpu().numpy(), phys[:, CONTACT_SLICE].cpu().numpy())
        steps = torch.from_numpy(mask[1:] & mask[:-1])[None].to(self.device)
        speed = planted_feet_loss(lambda j: j, steps, joints[None], keep_weight=0.0)
        before = float(speed(joints[None])) ** 0.5
        if before < STILL_FEET_MPS:
            return features, {"evaluations": 0, "planted_speed_mps": [round(before, 4)] * 2}
        feet = planted_feet_loss(joints_of, steps, joints[None])
        loss = feet if also is None else (lambda latent: feet(latent) + also(latent))
        z = refine(loss, z.float().contiguous(), self.foot_refine)
        refined = self.vae.decode(z)[0]
        after = float(speed(features_to_joints(self.normalizer.denormalize(refined[0].float()))[None])) ** 0.5
        return refined, {"evaluations": self.foot_refine, "planted_speed_mps": [round(before, 4), round(after, 4)]}

    # ------------------------------------------------------------ generation
    def generate(self, prompt: str, seconds: float | str | None = None, seed: int = 0, steps: int | None = None,
                 cfg: float = 7.5, sampler: str = "ddim", batch: int = 1, return_attention: bool = False,
                 progress: Progress | None = None, foot_lock: bool = True, foot_refine: bool = True):
        """Text -> Motion (or a list of `batch` motions). seconds=None (or "auto") lets the model choose the
        length within a band around the training data's (a motion that ends outside it is sampled again
        at its edge, as with seconds = that length; DDIM and DPM-Solver++ tell after LENGTH_SETTLED of their
        steps and stop there), "model" takes the model's own, "prior" the
        training data's (frames_for); foot_lock=False returns the decoder's joints without the foot
        clean-up; foot_refine=False returns them before the planted-feet refinement, which
        refine_feet(motion) then runs (a preview first). sampler: "ddim" (the paper's), "dpm"
        (DPM-Solver++), "dpm-sde" (its stochastic form, fresh noise at each step) or "consistency" (the distilled
        student, 1-4 steps, one forward per step); steps=None is the sampler's default (DEFAULT_STEPS)."""
        prompt = self.check_prompt(prompt)
        frames = self.frames_for(seconds, prompt)
        steps, cfg, sampler, batch = self.check_sampling(steps, cfg, sampler, batch)
        seed = self.check_seed(seed)
        band = self._band_for(seconds, prompt)
        run = partial(self._generate, prompt, seed=seed, steps=steps, cfg=cfg, sampler=sampler, batch=batch,
                      return_attention=return_attention, progress=progress, foot_lock=foot_lock,
                      foot_refine=foot_refine)
        try:
            motions = run(frames, length=self.length_source(seconds),
                          watch=self._length_watch(band, steps, sampler) if batch == 1 else None)
            spent = steps
        except _LengthLeftBand as left:
            if return_attention and self.records(sampler):      # an edit of it goes straight to the band's edge
                self.source_runs.put(self.source_key(prompt, frames, seed, steps, cfg, sampler),
                                     SourceRun(held_frames=left.frames, band=band))
            motions = run(left.frames, length="held", progress=continued(progress, left.steps))
            spent = left.steps + steps
        for b, m in enumerate(motions):
            held = self._held_length(band, m.frames)
            if held is not None:
                motions[b] = run(held, length="held", row=b, progress=continued(progress, spent))[0]
                spent += steps
        return motions[0] if batch == 1 else motions

    def _generate(self, prompt: str, frames: int | None, seed: int, steps: int, cfg: float, sampler: str,
                  batch: int, return_attention: bool, progress: Progress | None, foot_lock: bool, length: str,
                  row: int | None = None, foot_refine: bool = True, watch=None) -> list[Motion]:
        """generate's sampling, on checked arguments; row: only that row of the batch's noise; watch: denoise's."""
        canvas = frames or self.canvas_frames
        noise = self.noise(batch, canvas, seed)
        alone = batch == 1          # one motion's run, also when it is sampled again at its band's edge (row 0)
        if row is not None:
            noise, batch = noise[row:row + 1], 1
        text = self.sampler_text([prompt] * batch, sampler)
        rows = self.conditional_rows(batch, sampler)
        store = AttentionStore(text, rows=rows, frames=canvas) if return_attention else None
        # a motion whose maps are asked for is likely edited next: its run is kept for the edit to replay (one sampled
        # again at its band's edge too: an edit of it goes to that edge, with that length in its source key); a row
        # of a batch is not, as its fresh noise per step is not the batch's
        recorder = (SourceRecorder(rows, observers=[store])
                    if store is not None and alone and self.records(sampler) else None)
        on_step = _stepped(progress, recorder)
        with self.network(sampler).controlled(recorder or store):
            z = self.denoise(text, noise, sampler, steps, cfg, auto=frames is None, seed=seed, on_step=on_step,
                             watch=watch)
        motions = self.decode(z, frames, [prompt] * batch, seed, foot_lock, length=length,
                              feet="refine" if foot_refine else "defer")
        if store is not None:
            for b, m in enumerate(motions):
                m.attention = store.maps(b, frames=m.frames)
        if recorder is not None:
            recorder.run.attention = store.maps(0)
            self.source_runs.put(self.source_key(prompt, frames, seed, steps, cfg, sampler), recorder.run)
        return motions

    @torch.no_grad()
    def generate_batch(self, prompts: list[str], frames: list[int], seed: int = 0, steps: int | None = None,
                       cfg: float = 7.5, sampler: str = "ddim", foot_lock: bool = True) -> list[Motion]:
        """Several prompts with their own lengths (frames, multiples of 4) in one batched
        sampling run, padded and masked in time: the evaluation protocol's workhorse."""
        if len(prompts) != len(frames) or not prompts:
            raise ValueError("give one length per prompt")
        prompts = [self.check_prompt(p) for p in prompts]
        steps, cfg, sampler, _ = self.check_sampling(steps, cfg, sampler)
        seed = self.check_seed(seed)
        for n in frames:
            if n % 4 or not MIN_AUTO_FRAMES <= n <= self.canvas_frames:
                raise ValueError(f"lengths must be multiples of 4 in {MIN_AUTO_FRAMES}..{self.canvas_frames}, got {n}")
        B, T = len(prompts), max(frames)
        text = self.sampler_text(prompts, sampler)
        mask = (torch.arange(T // 4)[None] < torch.tensor(frames)[:, None] // 4).to(self.device)
        noise = self.noise(B, T, seed) * mask[:, :, None, None]
        z = self.denoise(text, noise, sampler, steps, cfg, auto=False, seed=seed, frame_mask=mask)
        out = []
        for b, n in enumerate(frames):
            out += self.decode(z[b:b + 1, : n // 4], n, [prompts[b]], seed, foot_lock)
        return out

    # ------------------------------------------------------------ guided control
    def control(self, prompt: str, targets=None, mask=None, seed: int = 0, strength: float = 1.0,
                steps: int | None = None, cfg: float = 7.5, sampler: str = "ddim", repeats=None, signal=None,
                progress: Progress | None = None,
                edit: EditSpec | dict | None = None,
                gradient_steps: int | None = None, refine_steps: int | None = None,
                foot_lock: bool = True, foot_refine: bool = True) -> Motion | EditResult:
        """Text -> motion that also meets joint position targets (MoLA's training-free guidance).

        targets (T, 22, 3) metres and mask (T, 22) or (T, 22, 3) bool, or a ready
        `signal` (salad.motion.control). The motion has T frames (rounded down to a
        multiple of 4). strength scales the guidance step; repeats is the number of
        time-travel repeats per step (an int, or a function of (step, steps));
        gradient_steps the guidance steps per network evaluation and refine_steps those
        on the final latent (defaults in salad.diffusion.guidance: fewer refinement steps for the
        student, which is there to be fast). sampler "ddim" (steps default 50)
        or "consistency" (the distilled student, steps default 4, no time travel: `repeats` is
        not used). The planted feet are refined with the targets kept (CONTROL_FEET_TARGETS);
        foot_refine=False leaves that to refine_feet (see generate).

        edit runs an attention edit during guided sampling: an EditSpec, such as
        EditSpec(mode="mirror", mirror="upper") or EditSpec(target="a person runs forward"), or a
        dict with its fields as keys ({"mode": "mirror", "mirror": "upper"}). The source and the
        edited branch start from the same noise, run in one batch and both follow the
        targets; an EditResult with both motions is returned instead of a Motion.
        """
        prompt = self.check_prompt(prompt)
        sig = signal if signal is not None else make_signal(targets, mask)
        frames = (sig.frames // 4) * 4
        if not MIN_AUTO_FRAMES <= frames <= self.canvas_frames:
            raise ValueError(f"control signals must span {MIN_AUTO_FRAMES}..{self.canvas_frames} frames, got {sig.frames}")
        if not isinstance(strength, (int, float)) or not math.isfinite(strength) or not 0 <= strength <= 100:
            raise ValueError(f"strength must be a number in 0..100, got {strength!r}")
        if sampler not in ("ddim", "consistency"):
            raise ValueError(f"guided control samples with ddim or consistency, got {sampler!r}")
        if sampler == "consistency" and repeats is not None:
            raise ValueError("time-travel repeats apply to ddim; the consistency sampler makes one clean estimate "
                             "per step")
        steps, cfg, sampler, _ = self.check_sampling(steps, cfg, sampler)
        seed = self.check_seed(seed)
        if not sig.mask[:frames].any():
            raise ValueError(f"the control signal constrains nothing in its first {frames} frames")
        if edit is None:
            text, plan, prompts = self.sampler_text([prompt], sampler), None, [prompt]
        else:
            text, plan, prompts = self._control_edit(prompt, edit, steps, frames, sampler)

        def joints_of(z0: torch.Tensor) -> torch.Tensor:
            feats, _ = self.vae.decode(z0 / self.latent_scale)
            return features_to_joints(self.normalizer.denormalize(feats))

        loss = position_loss(joints_of, torch.from_numpy(sig.targets[:frames]).to(self.device),
                             torch.from_numpy(sig.mask[:frames]).to(self.device))
        g = torch.Generator().manual_seed(int(seed) + 1)
        on_step = (lambda i, n, x: progress(i, n)) if progress else None
        noise = self.noise(1, frames, seed).repeat(len(prompts), 1, 1, 1)     # one z_T for both edit branches
        gradient_steps = DEFAULT_GRADIENT_STEPS if gradient_steps is None else gradient_steps
        if refine_steps is None:
            refine_steps = STUDENT_REFINE_STEPS if sampler == "consistency" else DEFAULT_REFINE_STEPS
        with self.network(sampler).controlled(None if plan is None else plan.controller):
            if sampler == "consistency":
                z = guided_consistency_sample(self.student_fn(text, False, cfg), noise, self.schedule, loss, steps,
                                              strength, gradient_steps, refine_steps, generator=g,
                                              shared_noise=plan is not None, on_step=on_step)
            else:
                z = guided_sample(self.model_fn(text, auto=False), noise, self.schedule, loss, steps=steps,
                                  cfg_scale=cfg, strength=strength,
                                  repeats=default_repeats if repeats is None else repeats,
                                  gradient_steps=gradient_steps, refine_steps=refine_steps, generator=g,
                                  shared_noise=plan is not None,
                                  before_model=None if plan is None else step_follower(plan.controller),
                                  on_step=on_step)
        # the planted-feet refinement keeps the targets: their loss joins its own (CONTROL_FEET_TARGETS)
        motions = self.decode(z, frames, prompts, seed, foot_lock, project=False,
                              feet="refine" if foot_refine else "defer",
                              feet_also=lambda latent: CONTROL_FEET_TARGETS * loss(latent * self.latent_scale))
        if not all(np.isfinite(m.joints).all() for m in motions):
            raise ValueError(f"guided sampling diverged (strength {strength}, {steps} steps): "
                               "lower the strength or use more steps")

        def note_errors(m: Motion) -> Motion:
            err = control_errors(m.joints, sig)
            m.info.update(control_mean_error_m=float(err.mean()), control_max_error_m=float(err.max()),
                          control_strength=float(strength), control_refine_steps=int(refine_steps))
            return m
        for m in motions:
            note_errors(m)
            if m.pending_refinement is not None:        # the errors of the refined motion, once it comes
                m.pending_refinement = (lambda refine: lambda: note_errors(refine()))(m.pending_refinement)
        if plan is None:
            return motions[0]
        source, edited = motions
        source.attention, edited.attention = plan.store.maps(0, source.frames), plan.store.maps(1, edited.frames)
        params = dict(plan.params, seed=seed, steps=steps, cfg=cfg, sampler=sampler, strength=strength)
        return EditResult(source, edited, source.attention, edited.attention, params)

    def _control_edit(self, prompt: str, edit: EditSpec | dict, steps: int, frames: int, sampler: str):
        """Encoded text, edit plan and the two branch prompts for Pipeline.control(edit=...)."""
        spec = EditSpec.of(edit)
        prompt, target = self.check_edit(prompt, spec)
        text = self.sampler_text([prompt, target], sampler)
        self.resolve_hold(spec, prompt, target, unsupported="guided control")
        plan = build_edit(text, steps, frames, spec, prompt, target, cfg_layout=sampler != "consistency")
        return text, plan, [prompt, target]

    # ------------------------------------------------------------ editing
    def check_edit(self, source_prompt: str, spec: EditSpec) -> tuple[str, str]:
        """The cleaned source and edited prompts of an edit, or a clear error."""
        source_prompt = self.check_prompt(source_prompt)
        return source_prompt, self.check_prompt(spec.target_prompt(source_prompt))

    def resolve_hold(self, spec: EditSpec, source_prompt: str, target_prompt: str,
                     unsupported: str | None = None) -> str | None:
        """The body parts an edit holds to its source. "auto" holds the lower body when the edit re-weights
        words of an unchanged prompt whose action the vocabulary knows as done in place (a re-weighted
        manner word must not make a standing action walk off), and nothing otherwise. `unsupported`
        names an editing path that does not blend latents: there "auto" holds nothing and a part is an error."""
        if unsupported is not None:
            if spec.hold not in (None, "auto"):
                raise ValueError(f"hold={spec.hold!r} applies to Pipeline.edit; {unsupported} does not hold parts")
            return None
        if spec.hold != "auto":
            return spec.hold
        if spec.mode != "reweight" or target_prompt != source_prompt or self.prompt_check is None:
            return None
        return "lower" if self.prompt_check.in_place(source_prompt) else None

    def edit(self, source_prompt: str, target_prompt: str | None = None, mode: str = "swap", seed: int = 0,
             seconds: float | str | None = None, steps: int | None = None, cfg: float = 7.5, sampler: str = "ddim",
             tau: float | None = None, reweight: dict[str, float] | None = None, mirror: str | None = None,
             self_inject: float = DEFAULT_SELF_INJECT, hold: str | None = "auto", progress: Progress | None = None,
             foot_lock: bool = True, spec: EditSpec | None = None, foot_refine: bool = True) -> EditResult:
        """Zero-shot edit by cross-attention modulation (SALAD Algorithm 1).

        mode: "swap" (target_prompt replaces words; the source's maps lead while the
        timestep t >= tau * T, so the default tau = 0.8 means the first 20% of the steps),
        "refine" (target_prompt adds words; the aligned source maps are used while
        t >= tau * T, default 0 = every step), "reweight" (reweight={"word": s}, s in [-3, 3]) or "mirror" (mirror=
        "lower" | "upper" | "all"). reweight and mirror also compose with swap/refine.
        hold: body parts ("lower": root and legs, "upper") whose latents follow the source at every step;
        "auto" holds the lower body when re-weighting a prompt whose action is done in place (resolve_hold).
        Source and edited branches, with their CFG rows, run in one batched forward
        from the same noise. Where the source branch was sampled before with the same seed, length, steps, cfg
        and sampler settings (a generate with return_attention=True, or an earlier edit of it; the teacher's
        samplers, the last SOURCE_RUNS kept in self.source_runs), it is replayed from that record and the edited
        branch runs alone, two rows instead of four (edited.info["source_replayed"]).
        Returns both motions and both attention maps.
        The edit may instead come as spec=EditSpec(...) (salad.editing.spec), without those keywords.
        foot_refine=False: both motions come before the planted-feet refinement (see generate).
        """
        spec = EditSpec.from_arguments(spec, mode=mode, target=target_prompt, tau=tau, reweight=reweight,
                                       mirror=mirror, self_inject=self_inject, hold=hold)
        source_prompt, target_prompt = self.check_edit(source_prompt, spec)
        frames = self.frames_for(seconds, source_prompt)
        steps, cfg, sampler, _ = self.check_sampling(steps, cfg, sampler)
        seed = self.check_seed(seed)
        canvas = frames or self.canvas_frames

        band = self._band_for(seconds, source_prompt)

        def again_at(held: int, spent: int) -> EditResult:      # both branches again, at the source's band edge
            again = self.edit(source_prompt, seed=seed, seconds=held / FPS, steps=steps, cfg=cfg, sampler=sampler,
                              progress=continued(progress, spent), foot_lock=foot_lock, spec=spec,
                              foot_refine=foot_refine)
            again.source.info["length"] = again.edited.info["length"] = "held"
            return again

        key = self.source_key(source_prompt, frames, seed, steps, cfg, sampler)
        replay = self.source_runs.get(key) if self.records(sampler) else None
        if replay is not None and replay.held_frames is not None:
            if replay.band == band:         # the source's length left this band: straight to its edge
                return again_at(replay.held_frames, 0)
            replay = None                   # the same sampling held to no band ("model" length) runs whole

        text = self.sampler_text([source_prompt, target_prompt], sampler)
        plan = build_edit(text, steps, canvas, spec, source_prompt, target_prompt,
                          cfg_layout=sampler != "consistency",
                          hold=self.resolve_hold(spec, source_prompt, target_prompt),
                          replay=replay, record=replay is None and self.records(sampler))

        noise = self.noise(1, canvas, seed)
        if replay is None:
            noise = noise.repeat(2, 1, 1, 1)        # the same z_T for both branches
        on_step = _stepped(progress, plan.recorder)

        # a replayed source already kept to its band (it was recorded whole), so only a fresh one is watched
        watch = None if replay is not None else self._length_watch(band, steps, sampler)
        try:
            with self.network(sampler).controlled(plan.controller):
                z = self.denoise(plan.text, noise, sampler, steps, cfg, auto=frames is None, seed=seed,
                                 shared_noise=True, on_step=on_step, blend=plan.blend, watch=watch)
        except _LengthLeftBand as left:
            if plan.recorder is not None:
                self.source_runs.put(key, SourceRun(held_frames=left.frames, band=band))
            return again_at(left.frames, left.steps)
        if replay is not None:
            z = torch.cat((replay.latents[-1].to(z), z))
        source, edited = self.decode(z, frames, [source_prompt, target_prompt], seed, foot_lock,
                                     length=self.length_source(seconds), feet="refine" if foot_refine else "defer")
        if plan.recorder is not None:
            plan.recorder.run.attention = plan.store.maps(0)
            self.source_runs.put(key, plan.recorder.run)
        held = self._held_length(band, source.frames)
        if held is not None:
            return again_at(held, steps)
        source.attention, edited.attention = plan.maps(source.frames, edited.frames)
        edited.info["source_replayed"] = replay is not None
        params = dict(plan.params, seed=seed, steps=steps, cfg=cfg, sampler=sampler)
        return EditResult(source, edited, source.attention, edited.attention, params)

    def edit_real(self, motion, source_prompt: str, target_prompt: str | None = None, mode: str = "swap",
                  **params) -> EditResult:
        """Edit a real motion (BVH path, (T,22,3) joints or (T,263) features) by text: VAE encoding,
        inversion (negative-prompt by default), then the attention edit (keywords as Pipeline.edit, or
        spec=EditSpec(...)). `.source` is the reconstruction. See salad.editing.real.edit_real for the
        parameters."""
        return edit_real(self, motion, source_prompt, target_prompt, mode, **params)



def _stepped(progress: Progress | None, recorder: SourceRecorder | None):
    """A denoise on_step that reports progress and hands the recorded row's latents (the batch's first)
    to `recorder`; None where neither is there."""
    if progress is None and recorder is None:
        return None

    def on_step(i: int, n: int, x: torch.Tensor) -> None:
        if recorder is not None:
            recorder.step(x[:1])
        if progress is not None:
            progress(i, n)
    return on_step


def _length_keyword(seconds) -> str | None:
    """"auto" (None too), "model" or "prior" where `seconds` names a way to choose the length, else None."""
    if seconds is None:
        return "auto"
    word = seconds.strip().lower() if isinstance(seconds, str) else None
    return word if word in ("auto", "model", "prior") else None


def end_of_motion(activation: np.ndarray, threshold: float = ACTIVATION_THRESHOLD) -> int:
    """Frames up to the first drop of the activation below `threshold` (at least
    MIN_AUTO_FRAMES, rounded down to a multiple of 4)."""
    below = np.flatnonzero(activation[MIN_AUTO_FRAMES:] < threshold)
    n = MIN_AUTO_FRAMES + int(below[0]) if below.size else len(activation)
    return max(MIN_AUTO_FRAMES, (n // 4) * 4)


def load_pipeline(path: str | os.PathLike | None = None, bf16: bool = True, text_encoder: str | dict | None = None,
                  threads: int | None = None, device: str | torch.device = "auto",
                  bf16_min_rows: int = BF16_MIN_ROWS, student: bool = True) -> Pipeline:
    """Load a model directory holding `vae/` and `denoiser/` checkpoints. path=None means the
    embedded model in assets/model (or $SALAD_MODEL). device: "auto" (a CUDA GPU when torch sees
    one, else the CPU), "cpu", "cuda" or "cuda:N"; the denoiser, the VAE and the text encoder run there.
    bf16: autocast where the device has native bf16, for forwards of at least bf16_min_rows rows.
    student=False leaves out the directory's consistency student (e.g. one of an earlier teacher, while its
    successor is distilled: Pipeline.use_student)."""
    device = resolve_device(device)     # a GPU that is not there fails before seconds of loading
    if threads:
        torch.set_num_threads(threads)
    root = Path(path or os.environ.get("SALAD_MODEL") or EMBEDDED_MODEL)
    if not (root / "vae").is_dir() or not (root / "denoiser").is_dir():
        where = "the embedded model" if path is None else str(root)
        raise CheckpointError(
            f"{where} was not found at {root}: expected {root}/vae and {root}/denoiser checkpoint directories "
            "(train them with `salad train vae` and `salad train denoiser`, see README)")
    vae, norm, scale, _ = load_vae(root / "vae")
    denoiser, doc = load_denoiser(root / "denoiser")
    cfg = doc["config"]
    # a VAE whose decoder was fine-tuned on frozen latents (SAN) still fits the denoiser
    if cfg.get("vae_checksum") and cfg["vae_checksum"] not in vae_latent_checksums(root / "vae"):
        raise CheckpointError(f"{root}: the denoiser was trained on a different VAE than {root / 'vae'}")
    encoder = load_text_encoder(text_encoder or cfg["text_encoder"])
    if encoder.dim != denoiser.config.text_dim:
        raise CheckpointError(f"{root}: the denoiser expects {denoiser.config.text_dim}-d text features but the "
                              f"{encoder.name} encoder gives {encoder.dim}")
    schedule = NoiseSchedule(from_dict(DiffusionConfig, cfg["diffusion"]))
    distilled, info = load_student(root, cfg, vae_latent_checksums(root / "vae")) if student else (None, {})
    return Pipeline(vae, norm, scale, denoiser, encoder, schedule, int(cfg["canvas_frames"]), bf16=bf16,
                    bf16_min_rows=bf16_min_rows, source=str(root), prompt_check=PromptCheck.load(root, encoder),
                    device=device, student=distilled, student_info=info)


def load_student(root: Path, teacher_config: dict, vae_checksums: set[str]) -> tuple[Denoiser | None, dict]:
    """The consistency student in root/consistency (None when there is none), checked against the
    model it must work with, and what it was distilled from (guidance range, teacher)."""
    path = root / "consistency"
    if not path.is_dir():
        return None, {}
    student, doc, info = load_consistency_student(path)
    bad = partner_mismatches(doc["config"], teacher_config, vae_checksums)
    if bad:
        raise CheckpointError(f"{path}: the student's {', '.join(bad)} differ from the denoiser's "
                              f"(VAE: {root / 'vae'}); redistil it")
    uses = info.get("default_for", [])
    if not isinstance(uses, list) or not set(uses) <= set(STUDENT_USES):
        raise CheckpointError(f"{path}/config.json: meta.consistency.default_for must be a list drawn from "
                              f"{', '.join(STUDENT_USES)}, got {uses!r}")
    return student, info
