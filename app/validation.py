"""Checks for every value a request can carry. Requests may come from the page or from any
API client, so nothing is assumed about their types; failures raise ValueError with a
message meant for the user."""
from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Real

from .settings import MAX_CFG, MAX_SEED, MAX_STEPS


@dataclass(frozen=True)
class GenerateRequest:
    prompt: str
    seconds: float | None       # None: the model chooses the length
    seed: int
    steps: int
    cfg: float
    sampler: str


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


def parse_generate(pipe, prompt, auto_length, seconds, seed, steps, cfg, sampler) -> GenerateRequest:
    """Validate the Generate panel's values against `pipe` (prompt length, vocabulary,
    duration range) and the studio's limits."""
    text = pipe.check_prompt(prompt)
    unknown = pipe.text_encoder.unknown_words(text)
    if unknown:
        listed = ", ".join(f"“{w}”" for w in unknown)
        raise ValueError(f"the text encoder cannot read {listed}; describe the motion in plain English words")
    duration = None
    if not _flag("automatic length", auto_length):
        if seconds is None:
            raise ValueError("seconds is required when the length is not automatic")
        duration = _number("seconds", seconds, -math.inf, math.inf)
        pipe.frames_for(duration)   # the pipeline's own range check and message
    n_steps = _integer("steps", steps, 1, MAX_STEPS)
    scale = _number("CFG scale", cfg, 0.0, MAX_CFG)
    n_steps, scale, sampler, _ = pipe.check_sampling(n_steps, scale, sampler)
    return GenerateRequest(prompt=text, seconds=duration, seed=_integer("seed", seed, 0, MAX_SEED),
                           steps=n_steps, cfg=scale, sampler=sampler)


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
