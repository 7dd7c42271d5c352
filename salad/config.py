"""Dataclass configs read from and written to TOML/JSON with strict key checking."""
from __future__ import annotations

import dataclasses
import json
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    pass


# settings that were renamed: a config or a run's stored state that uses the old name is told the new one
# (configs) or read under it (resuming, salad.training.loop)
RENAMED = {"adversarial_max_clips": "focus_max_clips", "adversarial_classes": "focus_classes",
           "adversarial_rows": "focus_rows"}


def renamed_keys(data: dict[str, Any]) -> dict[str, Any]:
    return {RENAMED.get(k, k): v for k, v in data.items()}


def training_identity(cfg: dict[str, Any], defaults: dict[str, Any] | None = None) -> dict[str, Any]:
    """The part of a training config (as stored with a run or a model) that makes it another model: run settings
    (threads, logging, checkpoint cadence) and a longer schedule (max_steps, to train on) do not; old key names
    read as their new ones. defaults (the config type's, as a dict): a config stored before a field existed reads
    as that field's default, which is what its run trained with, so adding a field orphans no run before it."""
    cfg = renamed_keys(cfg)
    if defaults is not None:
        cfg = _with_defaults(cfg, json.loads(json.dumps(defaults)))
    cfg = {k: v for k, v in cfg.items() if k != "run"}
    if isinstance(cfg.get("optim"), dict):
        cfg["optim"] = {k: v for k, v in cfg["optim"].items() if k != "max_steps"}
    return cfg


def _with_defaults(saved: dict, defaults: dict) -> dict:
    out = dict(saved)
    for key, value in defaults.items():
        if key not in out:
            out[key] = value
        elif isinstance(value, dict) and isinstance(out[key], dict):
            out[key] = _with_defaults(out[key], value)
    return out


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config") -> T:
    """Build dataclass `cls` from a dict; unknown keys and wrong types are errors."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    renamed = [f"{key} is now {RENAMED[key]}" for key in unknown if RENAMED.get(key) in fields]
    if renamed:
        raise ConfigError(f"{where}: renamed key(s): {'; '.join(renamed)}")
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            # A nested table overrides the field's own default (its default_factory), so keys it
            # leaves out keep the values this config chose, not the nested class's defaults.
            f = fields[name]
            base = f.default_factory() if f.default_factory is not dataclasses.MISSING else hint()
            merged = {**dataclasses.asdict(base), **value} if isinstance(value, dict) else value
            kwargs[name] = from_dict(hint, merged, f"{where}.{name}")
            continue
        origin = typing.get_origin(hint)
        base = hint if origin is None else origin
        if base is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if base in (list, tuple) and isinstance(value, list):
            value = base(value)
        if base in (int, float, str, bool, list, tuple, dict) and not isinstance(value, base):
            raise ConfigError(f"{where}.{name}: expected {base.__name__}, got {value!r}")
        kwargs[name] = value
    return cls(**kwargs)


def require(ok: bool, where: str, name: str, rule: str, value) -> None:
    """A config's range rule: ConfigError "<where><name> must be <rule>, got <value>" unless ok."""
    if not ok:
        raise ConfigError(f"{where}{name} must be {rule}, got {value!r}")


def validate(cfg, where: str = "") -> None:
    """Check a config's values against the ranges its dataclasses state (their `check(where)`), nested
    tables included, so that a bad value stops a run at its start rather than minutes or hours into it."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            validate(value, f"{where}{f.name}.")
    check = getattr(cfg, "check", None)
    if check is not None:
        check(where)


def to_dict(obj) -> dict[str, Any]:
    return dataclasses.asdict(obj)


def defaults_of(cfg) -> dict[str, Any] | None:
    """The defaults of cfg's config type as a dict (what training_identity fills a stored config's missing
    fields with); None for a config that is not a dataclass."""
    return to_dict(type(cfg)()) if dataclasses.is_dataclass(cfg) else None


def load_toml(cls: type[T], path: str | Path) -> T:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML ({e})") from None
    cfg = from_dict(cls, data, str(path))
    try:
        validate(cfg)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    return cfg


def apply_overrides(cfg, args) -> None:
    """The command line's --out-dir, --max-steps, --data, --bundle, --balance, --threads, --device, --seed and
    --vae, where given, win over the file; the result is validated again."""
    for flag, section, name in (("out_dir", "run", "out_dir"), ("max_steps", "optim", "max_steps"),
                                ("data", "data", "root"), ("bundle", "data", "bundle"), ("balance", "data", "balance"),
                                ("threads", "run", "threads"), ("device", "run", "device"), ("seed", "run", "seed"),
                                ("vae", None, "vae")):
        value = getattr(args, flag, None)
        if value is None or (not value and flag not in ("balance", "seed")):     # a balance or seed of 0 is a value
            continue
        target = getattr(cfg, section) if section else cfg
        if not hasattr(target, name):
            raise ConfigError(f"--{flag.replace('_', '-')} does not apply to a {type(cfg).__name__}")
        setattr(target, name, value)
    validate(cfg)
