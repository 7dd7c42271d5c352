"""Build a HumanML3D-format dataset from a folder of one's own captioned BVH files.

`build_bvh(folder, out)` finds every *.bvh under the folder (recursively, skipping
hidden folders and files), imports each with a joint mapping ("auto" detects the
skeleton from its joint names), resamples to 20 fps, retargets every clip onto one
skeleton (the median bone lengths of the set), canonicalises it, computes the 263-d
features and, unless mirror=False, a mirrored copy M<id> with left/right swapped in
its captions. The output has the same layout as the Bandai build (new_joint_vecs/,
new_joints/, texts/, train/val/test.txt, Mean/Std from train, skeleton.json,
build_report.json) plus sources.json (id -> source file, split, mapping used); it is
written in a hidden sibling folder, renamed into place at the end, and an
interrupted build resumes where it stopped.

Captions. A clip `walks/slow.bvh` takes its captions from exactly one of:
  * `walks/slow.txt` next to it: one caption per line;
  * `captions.json` at the folder's root (or the file given as `captions`): an object
    {"walks/slow.bvh": ["a person walks slowly", ...]} keyed by the path relative
    to the folder with "/" separators (".bvh" may be left off); a single string is
    one caption.
Each caption is plain text, or a HumanML3D line `caption#tokens#start#end`, where the
tokens may be empty or left out (`caption#start#end`) and start/end in seconds mark
the part of the clip the caption describes (0#0: the whole clip). Clips without
captions are skipped and listed in build_report.json (or kept with no captions when
allow_uncaptioned=True: the VAE can learn from them, text-to-motion training cannot).

Ids are the relative path without ".bvh", with "/" and any character outside
[A-Za-z0-9._-] turned into "_"; clashing ids get a short hash of their path.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

from ..motion import representation as rep
from ..motion.bvh_mapping import MAPPINGS, validate_mapping
from ..motion.bvh_parse import BvhError
from .build import BuildError, check_output, convert_clips, finish_build, source_fingerprint, start_build
from .captions import swap_left_right, tag_tokens
from .dataset import Caption, DatasetError, parse_caption_line

CAPTIONS_JSON = "captions.json"
SPLITS = ("train", "val", "test")
CAPTION_HELP = ("give each clip captions in <clip>.txt next to it (one per line) or in captions.json at the "
                "folder's root ({\"path/clip.bvh\": [\"a person ...\"]})")


@dataclass
class BvhSource:
    name: str                          # output id
    path: Path
    rel: str                           # path relative to the folder, "/" separators
    captions: list[Caption] | None     # None: no captions found
    captions_from: str | None          # the file they came from


# ---------------------------------------------------------------- captions

def parse_caption(text: str, where: str) -> Caption:
    """A caption: plain text, `caption#tokens#start#end` or `caption#start#end`."""
    text = " ".join(text.split())  # a caption is one line of texts/<id>.txt
    if "#" not in text:
        return Caption(text, "", 0.0, 0.0)
    parts = text.split("#")
    try:
        if len(parts) == 3:
            if not parts[0].strip():
                raise DatasetError(f"{where}: empty caption in {text!r}")
            start, end = (float(x) if x.strip() else 0.0 for x in parts[1:])
            cap = Caption(parts[0].strip(), "", start, end)
        elif len(parts) >= 4:
            cap = parse_caption_line(text, where)
        else:
            raise DatasetError(f"{where}: {text!r} has one '#'")
    except (DatasetError, ValueError) as e:
        msg = str(e) if isinstance(e, DatasetError) else f"{where}: bad timestamps in {text!r}"
        raise BuildError(f"{msg}; a caption is plain text without '#', or caption#tokens#start#end "
                         f"(tokens may be empty or left out)") from None
    if not (math.isfinite(cap.start) and math.isfinite(cap.end)) or cap.start < 0 or \
            (cap.end != 0.0 and cap.end <= cap.start):
        raise BuildError(f"{where}: timestamps {cap.start:g}..{cap.end:g} in {text!r} are not a time span "
                         f"in seconds (0#0 means the whole clip)")
    return cap


def read_caption_file(path: Path) -> list[Caption]:
    """Captions of a <clip>.txt file, one per non-blank line."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise BuildError(f"{path}: cannot read the captions ({e})") from None
    return [parse_caption(line, f"{path}:{k}") for k, line in enumerate(lines, 1) if line.strip()]


def read_captions_json(path: Path, rels: Sequence[str]) -> dict[str, list[Caption]]:
    """{relative .bvh path: captions} from a captions.json keyed by relative path."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise BuildError(f"{path}: cannot read the captions ({e})") from None
    if not isinstance(doc, dict):
        raise BuildError(f"{path}: expected an object {{\"path/clip.bvh\": [\"caption\", ...]}}")
    by_key = {}
    for rel in rels:
        by_key[rel] = rel
        by_key.setdefault(rel[: -len(Path(rel).suffix)], rel)
    out, unknown = {}, []
    for key, value in doc.items():
        rel = by_key.get(key.replace("\\", "/").removeprefix("./"))
        if rel is None:
            unknown.append(key)
            continue
        values = [value] if isinstance(value, str) else value
        if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
            raise BuildError(f"{path}: captions of {key!r} must be a string or a list of strings")
        if rel in out:
            raise BuildError(f"{path}: {rel} is listed twice (with and without .bvh)")
        out[rel] = [parse_caption(v, f"{path}[{key!r}]") for v in values if v.strip()]
    if unknown:
        raise BuildError(f"{path}: no BVH file for {len(unknown)} entries, e.g. {unknown[:5]}; keys are paths "
                         f"relative to {path.parent} with '/' separators")
    return out


def caption_text_line(cap: Caption, mirrored: bool = False) -> str:
    """The texts/<id>.txt line of a caption (tokens tagged here when the caption had none)."""
    text, tokens = cap.text, cap.tokens or tag_tokens(cap.text)
    if mirrored:
        text, tokens = swap_left_right(text), swap_left_right(tokens)
    return f"{text}#{tokens}#{_seconds(cap.start)}#{_seconds(cap.end)}"


def _seconds(x: float) -> str:
    return f"{x:.1f}" if round(x, 1) == x else f"{x:g}"


# ---------------------------------------------------------------- discovery

def _clip_ids(rels: Sequence[str]) -> dict[str, str]:
    base = {}
    for rel in rels:
        stem = re.sub(r"[^A-Za-z0-9._-]", "_", rel[: -len(Path(rel).suffix)]).lstrip(".-")
        base[rel] = stem or "clip"
    keys = Counter(b.casefold() for b in base.values())
    # "M<id>" names the mirror of <id>, so an id may not equal "M" + another id either.
    clash = {rel for rel, b in base.items()
             if keys[b.casefold()] > 1 or (b[:1] in "Mm" and b[1:].casefold() in keys)
             or ("m" + b.casefold()) in keys}
    ids = {rel: f"{b}-{hashlib.sha1(rel.encode()).hexdigest()[:8]}" if rel in clash else b for rel, b in base.items()}
    if len({i.casefold() for i in ids.values()}) != len(ids):
        raise BuildError(f"clip ids clash even with path hashes: {sorted(ids.values())}")
    return ids


def discover_bvh(root: str | Path, captions: str | Path | None = None) -> list[BvhSource]:
    """Every *.bvh under root with its captions (None where it has none)."""
    root = Path(root)
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() == ".bvh" and p.is_file()
                   and not any(part.startswith(".") for part in p.relative_to(root).parts))
    rels = [p.relative_to(root).as_posix() for p in files]
    json_path = Path(captions) if captions is not None else root / CAPTIONS_JSON
    if captions is not None and not json_path.is_file():
        raise BuildError(f"{json_path}: captions file not found")
    from_json = read_captions_json(json_path, rels) if json_path.is_file() else {}
    ids = _clip_ids(rels)
    out = []
    for path, rel in zip(files, rels):
        side = path.with_suffix(".txt")
        caps, where = None, None
        if side.is_file():
            caps, where = read_caption_file(side), side.name
            if rel in from_json:
                raise BuildError(f"{rel}: captions both in {side} and in {json_path}; keep one")
        elif rel in from_json:
            caps, where = from_json[rel], json_path.name
        out.append(BvhSource(ids[rel], path, rel, caps or None, where if caps else None))
    return out


# ---------------------------------------------------------------- splits and mappings

def _split_fractions(fractions: Sequence[float]) -> list[float]:
    try:
        fr = [float(f) for f in fractions]
    except (TypeError, ValueError):
        fr = []
    if len(fr) != 3 or any(not math.isfinite(f) or f < 0 for f in fr) or abs(sum(fr) - 1) > 1e-6 or fr[0] <= 0:
        raise BuildError(f"split fractions must be three shares (train, val, test) >= 0 summing to 1 with "
                         f"train > 0, got {fractions!r}")
    return fr


def random_splits(names: Sequence[str], fractions: Sequence[float] = (0.8, 0.05, 0.15),
                  seed: int = 0) -> dict[str, str]:
    """Train/val/test by seeded hash order: the counts follow `fractions` (every split with a
    positive share gets a clip when there are enough), and adding clips moves few others."""
    fr = _split_fractions(fractions)
    n = len(names)
    exact = [f * n for f in fr]
    counts = [int(math.floor(x)) for x in exact]
    for k in sorted(range(3), key=lambda k: counts[k] - exact[k])[: n - sum(counts)]:
        counts[k] += 1
    for k in (1, 2):
        if fr[k] > 0 and counts[k] == 0 and n >= 1 + sum(f > 0 for f in fr[1:]):
            donor = max(range(3), key=lambda i: counts[i])
            counts[donor] -= 1
            counts[k] += 1
    order = sorted(names, key=lambda name: hashlib.sha256(f"{seed}\0{name}".encode()).digest())
    bounds = [counts[0], counts[0] + counts[1]]
    return {name: SPLITS[0 if i < bounds[0] else 1 if i < bounds[1] else 2] for i, name in enumerate(order)}


def resolve_mapping_arg(mapping: str | Path | Mapping) -> str | dict:
    """"auto", a built-in mapping's name, a JSON file {joint: source name}, or such a dict."""
    if isinstance(mapping, Mapping):
        try:
            return validate_mapping(mapping, "mapping")
        except BvhError as e:
            raise BuildError(str(e)) from None
    text = str(mapping)
    if text == "auto" or text in MAPPINGS:
        return text
    path = Path(text)
    if path.suffix.lower() != ".json" and not path.is_file():
        raise BuildError(f"unknown mapping {text!r}; use 'auto', one of {sorted(MAPPINGS)}, or a JSON file "
                         f"{{\"pelvis\": \"Hips\", ...}} naming the source joint of each of the 22 joints")
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise BuildError(f"{path}: cannot read the joint mapping ({e})") from None
    try:
        return validate_mapping(doc, str(path))
    except BvhError as e:
        raise BuildError(str(e)) from None


# ---------------------------------------------------------------- build

def _why_uncaptioned(s: BvhSource) -> str:
    side = s.path.with_suffix(".txt")
    if side.is_file():
        return f"{s.path}: no captions ({side.name} is empty)"
    return f"{s.path}: no captions (neither {side.name} next to it nor an entry in {CAPTIONS_JSON})"


def build_bvh(source_dir: str | Path, out: str | Path, mapping: str | Path | Mapping = "auto", mirror: bool = True,
              workers: int = 2, seed: int = 0, split: Sequence[float] = (0.8, 0.05, 0.15),
              captions: str | Path | None = None, allow_uncaptioned: bool = False, progress: bool = True) -> dict:
    """Build a HumanML3D-layout dataset at `out` from the captioned BVH files under
    `source_dir`; returns the build report (also written as build_report.json)."""
    root, out = Path(source_dir), Path(out)
    if not root.is_dir():
        raise BuildError(f"{root}: {'not a folder' if root.exists() else 'no such folder'}")
    check_output(root, out)
    table = resolve_mapping_arg(mapping)
    _split_fractions(split)
    found = discover_bvh(root, captions)
    if not found:
        raise BuildError(f"{root}: no .bvh files found (searched recursively, hidden folders skipped)")
    uncaptioned = [s.rel for s in found if s.captions is None]
    clips = found if allow_uncaptioned else [s for s in found if s.captions is not None]
    if not clips:
        raise BuildError(f"{root}: none of the {len(found)} BVH files has captions; {CAPTION_HELP}, "
                         f"or allow uncaptioned clips")
    skipped = {} if allow_uncaptioned else {s.rel: _why_uncaptioned(s) for s in found if s.captions is None}
    if progress:
        for why in skipped.values():
            print(f"skipped: {why}")

    out.parent.mkdir(parents=True, exist_ok=True)
    sources = {s.name: s.path for s in clips}
    work = start_build(out, {"builder": "bvh", "mapping": table, "mirror": bool(mirror),
                             "clips": source_fingerprint(sources)})
    conv = convert_clips(sources, work, mapping=table, mirror=mirror, workers=workers, progress=progress)
    by_name = {s.name: s for s in clips}
    skipped.update({by_name[n].rel: why for n, why in conv.skipped.items()})
    if not conv.built:
        shutil.rmtree(work, ignore_errors=True)  # nothing worth resuming
        reasons = list(conv.skipped.values())
        hint = ("; if the joints have other names, pass a mapping: a JSON file naming the source joint of each "
                "of the 22 joints") if any("do not match" in r for r in reasons) else ""
        raise BuildError(f"{root}: no BVH file could be imported; first problems: " + "; ".join(reasons[:3]) + hint)

    clip_split = random_splits(conv.built, split, seed)
    texts, splits, table_of_sources = {}, {}, {}
    for name in conv.built:
        s = by_name[name]
        for prefix in ("", "M") if mirror else ("",):
            texts[prefix + name] = [caption_text_line(c, bool(prefix)) for c in s.captions or []]
            splits[prefix + name] = clip_split[name]
            table_of_sources[prefix + name] = {"source": s.rel, "mirrored": bool(prefix), "split": clip_split[name],
                                               "mapping": conv.mappings[name], "captions_from": s.captions_from}
    report = {"source": str(root), "clips_found": len(found), "clips_built": len(conv.built),
              "clips_resumed": conv.resumed, "motions_written": len(texts),
              "skipped": dict(sorted(skipped.items())), "uncaptioned": uncaptioned,
              "mappings": dict(Counter(conv.mappings.values())), "mirror": bool(mirror),
              "split": dict(zip(SPLITS, map(float, split))),
              "clips_per_split": {k: sum(v == k for v in clip_split.values()) for k in SPLITS},
              "fps": rep.FPS, "seed": seed}
    return finish_build(work, out, texts, splits, report, {"sources.json": table_of_sources})
