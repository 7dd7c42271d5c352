"""Checks for every value a request can carry. Requests may come from the page or from any
API client, so nothing is assumed about their types; failures raise ValueError with a
message meant for the user."""
from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Real
from pathlib import Path
from typing import ClassVar

from salad.motion.control import lower_body_signal
from salad.motion.representation import FPS
from salad.editing.spec import EDIT_MODES, HOLD_CHOICES, EditSpec
from salad.pipeline import MIN_AUTO_FRAMES

from . import controls
from .real_input import RealInput, read_upload, upload_path
from .settings import (
    DEFAULT_SELF_INJECT, DEFAULT_TAU, MAX_CFG, MAX_PATH_SPEED, MAX_REWEIGHT, MAX_SEED, MAX_STEPS, MAX_STRENGTH,
    MIRROR_PARTS,
)


@dataclass(frozen=True)
class GenerateRequest:
    prompt: str
    seconds: float | None       # None: the model chooses the length
    seed: int
    steps: int
    cfg: float
    sampler: str
    foot_lock: bool = True      # clean-up after decoding: rigid bones, planted feet pinned (salad.motion.cleanup)


@dataclass(frozen=True)
class AttentionRequest:
    word: int | None            # index into the prompt's words; None: no word chosen
    layers: tuple[int, ...]
    steps: tuple[int, int]      # [start, stop) over the sampling steps, 0-based


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _number(name: str, value, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (Real, str)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if not lo <= x <= hi:
        raise ValueError(f"{name} must be between {_fmt(lo)} and {_fmt(hi)}, got {value!r}")
    return x


def _integer(name: str, value, lo: int, hi: int) -> int:
    x = _number(name, value, lo, hi)
    if x != int(x):
        raise ValueError(f"{name} must be a whole number, got {value!r}")
    return int(x)


def _flag(name: str, value) -> bool:
    if isinstance(value, bool):
        return value
    if value in (0, 1):
        return bool(value)
    raise ValueError(f"{name} must be true or false, got {value!r}")


def check_text(pipe, prompt, what: str = "prompt") -> str:
    """The pipeline's prompt check plus the text encoder's vocabulary; messages name `what`."""
    try:
        text = pipe.check_prompt(prompt)
    except ValueError as exc:
        msg = str(exc)
        if what != "prompt":
            msg = what + msg[len("prompt"):] if msg.startswith("prompt") else f"{what}: {msg}"
        raise ValueError(msg) from None
    unknown = pipe.text_encoder.unknown_words(text)
    if unknown:
        listed = ", ".join(f"“{w}”" for w in unknown)
        where = "" if what == "prompt" else f" in the {what}"
        raise ValueError(f"the text encoder cannot read {listed}{where}; describe the motion in plain English words")
    return text


def _duration(pipe, auto_length, seconds) -> float | None:
    if _flag("automatic length", auto_length):
        return None
    if seconds is None:
        raise ValueError("seconds is required when the length is not automatic")
    duration = _number("seconds", seconds, -math.inf, math.inf)
    pipe.frames_for(duration)   # the pipeline's own range check and message
    return duration


def _sampling(pipe, seed, steps, cfg, sampler) -> tuple[int, int, float, str]:
    n_steps = _integer("steps", steps, 1, MAX_STEPS)
    scale = _number("CFG scale", cfg, 0.0, MAX_CFG)
    n_steps, scale, sampler, _ = pipe.check_sampling(n_steps, scale, sampler)
    return _integer("seed", seed, 0, MAX_SEED), n_steps, scale, sampler


def parse_generate(pipe, prompt, auto_length, seconds, seed, steps, cfg, sampler,
                   foot_lock=True) -> GenerateRequest:
    """Validate the Generate panel's values against `pipe` (prompt length, vocabulary,
    duration range) and the studio's limits."""
    text = check_text(pipe, prompt)
    duration = _duration(pipe, auto_length, seconds)
    seed, n_steps, scale, sampler = _sampling(pipe, seed, steps, cfg, sampler)
    return GenerateRequest(prompt=text, seconds=duration, seed=seed, steps=n_steps, cfg=scale, sampler=sampler,
                           foot_lock=_flag("foot lock", foot_lock))


def parse_word(words: list[str], word) -> int | None:
    """A word by index (what the page sends) or by text (first occurrence, any case)."""
    if word is None or (isinstance(word, str) and not word.strip()):
        return None
    if isinstance(word, str):
        w = word.strip().lower()
        if w.lstrip("-").isdigit():
            return parse_word(words, int(w))
        if w not in words:
            raise ValueError(f"“{word}” is not a word of the prompt; choose one of: {', '.join(words)}")
        return words.index(w)
    return _integer("word", word, 0, len(words) - 1)


def parse_attention(maps, word, layers, first_step, last_step) -> AttentionRequest:
    """Validate an attention view of `maps` (salad AttentionMaps): the word, a non-empty set
    of captured layers and a 1-based inclusive range of sampling steps."""
    if layers is None or isinstance(layers, (str, bytes)) or not hasattr(layers, "__iter__"):
        raise ValueError(f"layers must be a list of layer numbers, got {layers!r}")
    chosen = sorted({_integer("layer", l, min(maps.layers), max(maps.layers)) for l in layers})
    if not chosen:
        raise ValueError("choose at least one layer")
    missing = [l for l in chosen if l not in maps.layers]
    if missing:
        raise ValueError(f"layers {missing} were not captured; choose from {maps.layers}")
    first = _integer("first step", first_step, 1, maps.steps)
    last = _integer("last step", last_step, 1, maps.steps)
    if first > last:
        raise ValueError(f"the first step ({first}) comes after the last step ({last})")
    return AttentionRequest(word=parse_word(maps.words, word), layers=tuple(chosen), steps=(first - 1, last))


BVH_UNITS = ("cm", "m")


def parse_bvh_units(units) -> str:
    """The length unit of the BVH downloads."""
    return _choice("BVH units", units, BVH_UNITS)


# ---------------------------------------------------------------- editing

class _Edit:
    """The edit settings a request carries, as the EditSpec the pipeline takes."""

    @property
    def spec(self) -> EditSpec:
        return EditSpec(mode=self.mode, target=self.target, tau=self.tau, reweight=self.reweight, mirror=self.mirror,
                        self_inject=self.self_inject, hold=self.hold)


@dataclass(frozen=True)
class EditRequest(_Edit):
    source: str
    target: str | None              # swap / refine: the edited prompt; None: the source prompt is kept
    mode: str                       # swap | refine | reweight | mirror
    tau: float | None               # swap / refine only
    reweight: tuple[tuple[str, float], ...]   # (word of the edited prompt, scale s)
    mirror: str | None              # lower | upper | all
    self_inject: float
    hold: str | None                # body parts held to the source: auto | lower | upper; None: none
    seconds: float | None
    seed: int
    steps: int
    cfg: float
    sampler: str
    foot_lock: bool = True

    @property
    def edited_prompt(self) -> str:
        return self.target or self.source


def _choice(name: str, value, options) -> str:
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"{name} must be one of {', '.join(options)}, got {value!r}")
    return value


def parse_edit(pipe, source, mode, target, tau, reweight_word, reweight_scale, mirror, self_inject, hold,
               auto_length, seconds, seed, steps, cfg, sampler, foot_lock=True) -> EditRequest:
    """Validate the Edit panel. swap and refine need a target prompt (swap: as many words as
    the source); re-weighting names a word of the edited prompt (required in reweight mode,
    optional with swap/refine); mirroring names a body half (all of it when mirror mode names none);
    `hold` names the body half held to the source, "auto" or "none"."""
    mode = _choice("edit mode", mode, EDIT_MODES)
    src = check_text(pipe, source, "source prompt")
    tgt, t = None, None
    if mode in ("swap", "refine"):
        if target is None or (isinstance(target, str) and not target.strip()):
            raise ValueError(f"{'word swap' if mode == 'swap' else 'refine'} needs a target prompt: "
                             + ("the source prompt with words replaced" if mode == "swap"
                                else "the source prompt with words added"))
        tgt = check_text(pipe, target, "target prompt")
        src_words, tgt_words = pipe.text_encoder.split_words(src), pipe.text_encoder.split_words(tgt)
        if src_words == tgt_words:
            raise ValueError("the target prompt has the same words as the source prompt; "
                             + ("replace a word" if mode == "swap" else "add words"))
        if mode == "swap" and len(src_words) != len(tgt_words):
            raise ValueError(f"word swap needs as many words in the target prompt as in the source "
                             f"({len(tgt_words)} vs {len(src_words)}); use refine to add words")
        t = _number("tau", DEFAULT_TAU[mode] if tau is None else tau, 0.0, 1.0)
    words = pipe.text_encoder.split_words(tgt or src)
    weights: tuple[tuple[str, float], ...] = ()
    chosen = reweight_word.strip().lower() if isinstance(reweight_word, str) else reweight_word
    if chosen not in (None, "", "none"):
        if not isinstance(chosen, str):
            raise ValueError(f"the word to re-weight must be text, got {reweight_word!r}")
        if chosen not in words:
            raise ValueError(f"cannot re-weight “{reweight_word}”: it is not a word of the "
                             f"{'target' if tgt else 'source'} prompt ({', '.join(words)})")
        weights = ((chosen, _number("re-weighting scale s", reweight_scale, -MAX_REWEIGHT, MAX_REWEIGHT)),)
    elif mode == "reweight":
        raise ValueError(f"choose the word to re-weight, one of: {', '.join(words)}")
    half = None if mirror in (None, "", "none") else _choice("mirror", mirror, MIRROR_PARTS)
    held = None if hold in (None, "", "none") else _choice("hold to the source", hold, HOLD_CHOICES + ("none",))
    spec = EditSpec(mode=mode, target=tgt, tau=t, reweight=weights, mirror=half,
                    self_inject=_number("self-attention injection", self_inject, 0.0, 1.0), hold=held)
    duration = _duration(pipe, auto_length, seconds)
    seed, n_steps, scale, sampler = _sampling(pipe, seed, steps, cfg, sampler)
    return EditRequest(source=src, target=tgt, mode=mode, tau=t, reweight=spec.reweight, mirror=spec.mirror,
                       self_inject=spec.self_inject, hold=spec.hold, seconds=duration, seed=seed, steps=n_steps,
                       cfg=scale, sampler=sampler, foot_lock=_flag("foot lock", foot_lock))


# ---------------------------------------------------------------- guided control

@dataclass(frozen=True)
class ControlRequest:
    prompt: str
    task: str                       # a key of app.controls.TASKS
    detail: tuple                   # what the signal is made from (preset + timing, file digest, keyframes...)
    base: str | None                # id of the generated motion the signal was taken from
    strength: float
    seed: int
    steps: int
    cfg: float
    foot_lock: bool = True
    sampler: str = "ddim"           # ddim, or consistency (the distilled student)


GUIDED_SAMPLERS = ("ddim", "consistency")     # what guided control and real-motion edits sample with


def _guided_sampler(what: str, sampler) -> str:
    """Control and real-motion edits take ddim or the student; None is ddim (what a client that
    predates the choice sends)."""
    sampler = "ddim" if sampler is None else sampler
    if sampler == "dpm":
        raise ValueError(f"{what} samples with ddim or consistency (the distilled student), not dpm")
    return _choice("sampler", sampler, GUIDED_SAMPLERS)


def control_signal(pipe, task, preset, seconds, speed, upload, example, keyframes, *, base=None,
                   upload_root=None, examples_dir=None):
    """Build the Control panel's signal -> (ControlSignal, detail, base id). `base` is the
    session's last generated Result (in-betweening and upper-body edits start from it);
    uploads must lie under `upload_root`; examples are file names in `examples_dir`."""
    task = _choice("task", task, tuple(controls.TASKS))
    span = (MIN_AUTO_FRAMES, pipe.canvas_frames)
    if task == "path":
        preset = _choice("path", preset, tuple(controls.PRESETS))
        frames = pipe.frames_for(_number("seconds", seconds, -math.inf, math.inf))
        v = _number("speed", speed, 0.1, MAX_PATH_SPEED)
        return controls.preset_signal(preset, frames, v, FPS), (preset, frames, v), None
    if task in ("mola", "targets"):
        up = controls.upload_file(upload, upload_root) if upload_root is not None else None
        if up is None and task == "mola" and example not in (None, ""):
            names = controls.list_examples(examples_dir)
            if example not in names:
                raise ValueError(f"“{example}” is not one of the control examples"
                                 + (f" ({', '.join(names)})" if names else " (none are installed)"))
            path, name, digest = Path(examples_dir) / example, example, "example"
        elif up is None:
            raise ValueError("upload a .npy file" + (" or choose an example" if task == "mola" else ""))
        else:
            path, name, digest = up.path, up.name, up.digest
        read = controls.mola_signal if task == "mola" else controls.target_signal
        return read(path, name, span, FPS), (name, digest), None
    if base is None:
        raise ValueError("generate a motion first (Generate tab): "
                         + ("its poses are the keyframes" if task == "inbetween" else "its lower body is kept"))
    joints = base.motion.joints
    if task == "inbetween":
        kept = controls.parse_keyframes(keyframes, len(joints))
        return controls.inbetween_signal(joints, kept), kept, base.id
    return lower_body_signal(joints), (), base.id   # an upper-body edit keeps the lower body


def parse_control(pipe, prompt, task, preset, seconds, speed, upload, example, keyframes, strength, seed,
                  steps, cfg, foot_lock=True, sampler="ddim", **where):
    """Validate the Control panel and build its signal -> (ControlRequest, ControlSignal);
    `where` are control_signal's keyword arguments. sampler: ddim, or consistency when the
    model has a distilled student."""
    text = check_text(pipe, prompt)
    sampler = _guided_sampler("guided control", sampler)
    signal, detail, base_id = control_signal(pipe, task, preset, seconds, speed, upload, example, keyframes, **where)
    seed, n_steps, scale, sampler = _sampling(pipe, seed, steps, cfg, sampler)
    req = ControlRequest(prompt=text, task=task, detail=detail, base=base_id,
                         strength=_number("strength", strength, 0.0, MAX_STRENGTH), seed=seed, steps=n_steps, cfg=scale,
                         foot_lock=_flag("foot lock", foot_lock), sampler=sampler)
    return req, signal


# ---------------------------------------------------------------- editing real motions

@dataclass(frozen=True)
class RealEditRequest(_Edit):
    input_name: str                 # the uploaded file's name or the test clip's id
    input_kind: str                 # bvh | joints | features | clip
    input_digest: str               # sha256 of the uploaded file, or the clip's id: equal inputs, equal requests
    source: str                     # describes the input
    target: str | None
    mode: str
    tau: float | None
    reweight: tuple[tuple[str, float], ...]
    mirror: str | None
    self_inject: float
    hold: ClassVar[None] = None     # real-motion editing holds no parts
    inversion: str | None           # a method of salad.diffusion.inversion; None with the student, which needs none
    steps: int
    cfg: float
    foot_lock: bool = True
    sampler: str = "ddim"           # ddim (after the inversion), or consistency: the student edits the encoded motion
    seed: int = 0                   # the student's noise; 0 with ddim, whose inversion is deterministic


def parse_real_edit(pipe, upload, clip, source, mode, target, reweight_word, reweight_scale, mirror, inversion,
                    steps, cfg, foot_lock=True, sampler="ddim", seed=0, *, upload_root: Path,
                    clips=None) -> tuple[RealEditRequest, RealInput]:
    """Validate the Real motion panel -> (RealEditRequest, app.real_input.RealInput). The motion is
    an upload (under `upload_root`) or a test clip of `clips` (an app.real_input.ClipLibrary),
    never both; the edit is checked as the Edit panel's, with the edit's default τ and
    self-attention injection, and sampled with DDIM as the inversion requires, or with the
    distilled student (sampler "consistency"), which needs no inversion: the inversion choice is
    then ignored and `seed` draws its noise."""
    from salad.diffusion.inversion import METHODS

    sampler = _guided_sampler("a real-motion edit", sampler)
    up = upload_path(upload, upload_root)
    picked = clip not in (None, "", "none")
    if up is not None and picked:
        raise ValueError("give either an uploaded motion or a test clip, not both")
    if up is not None:
        motion, digest = read_upload(up.path, up.name), up.digest
    elif picked:
        if clips is None:
            raise ValueError("no test clips are offered: start the studio with --clips DIR (a dataset build)")
        motion = clips.read(clip, pipe.canvas_frames)
        digest = f"clip:{motion.name}"
    else:
        raise ValueError("upload a motion (.bvh, or .npy joints or features)"
                         + (" or pick a test clip" if clips is not None else ""))
    student = sampler == "consistency"
    method = None if student else _choice("inversion", inversion, METHODS)
    ed = parse_edit(pipe, source, mode, target, None, reweight_word, reweight_scale, mirror, DEFAULT_SELF_INJECT, None,
                    True, None, seed if student else 0, steps, cfg, sampler, foot_lock)
    req = RealEditRequest(input_name=motion.name, input_kind=motion.kind, input_digest=digest, source=ed.source, target=ed.target,
                          mode=ed.mode, tau=ed.tau, reweight=ed.reweight, mirror=ed.mirror, self_inject=ed.self_inject,
                          inversion=method, steps=ed.steps, cfg=ed.cfg, foot_lock=ed.foot_lock, sampler=ed.sampler,
                          seed=ed.seed)
    return req, motion
