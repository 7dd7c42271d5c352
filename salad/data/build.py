"""Build a HumanML3D-format text-motion dataset from labelled BVH mocap.

`build_bandai(input, out)` reads the Bandai-Namco Research Motion datasets 1 and 2
(the .tar.xz archive or an unpacked folder) and writes:

    new_joint_vecs/<id>.npy   (T, 263) features       new_joints/<id>.npy  (T, 22, 3)
    texts/<id>.txt            captions                train.txt / val.txt / test.txt
    Mean.npy / Std.npy        train statistics        labels.json, skeleton.json, build_report.json

Every clip is retargeted onto one skeleton (the median bone lengths of the whole
set), canonicalised and converted to features; its mirror image is stored as
M<id> with left/right swapped in its labels and captions. The build happens in a
hidden sibling directory that is renamed into place at the end, so a crash never
leaves a half-written dataset; a rerun resumes from the clips already converted.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tarfile
import tempfile
from collections import Counter, defaultdict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..checkpoint import atomic_write_text
from ..motion import representation as rep
from ..motion.bvh import BvhError, load_bvh
from .captions import MIRRORED_CONTENT, caption_line, captions_for, swap_left_right

SPLIT_PATTERN = "TTTXTTTTTTXTTTVTTXTT"   # 16 train, 1 val, 3 test in every 20 clips of a stratum run
SPLIT_NAMES = {"T": "train", "V": "val", "X": "test"}
MIN_FRAMES = 16                          # 0.8 s at 20 fps
CAPTIONS_PER_CLIP = 3


class BuildError(RuntimeError):
    pass


@dataclass
class Clip:
    name: str          # output id, e.g. "b2_walk_normal_001"
    path: Path
    dataset: int
    content: str
    style: str


def _atomic_save_npy(path: Path, array: np.ndarray) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".npy")
    try:
        with os.fdopen(fd, "wb") as f:
            np.save(f, array)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------- discovery

def _unpack(archive: Path, into: Path) -> Path:
    with tarfile.open(archive, "r:*") as tar:
        members = [m for m in tar.getmembers()
                   if m.isfile() and (m.name.endswith((".bvh", ".json")) or "/cfg/" in m.name)]
        tar.extractall(into, members=members, filter="data")
    return into


def discover_bandai(root: Path) -> list[Clip]:
    """Find every labelled clip; labels come from the per-clip JSON and cfg/*_label.txt,
    cross-checked against the file name."""
    clips = []
    for ds_dir in sorted(root.rglob("Bandai-Namco-Research-Motiondataset-*")):
        if not ds_dir.is_dir():
            continue
        m = re.search(r"Motiondataset-(\d+)$", ds_dir.name)
        if not m or not (ds_dir / "data").is_dir():
            continue
        ds = int(m.group(1))
        contents = _read_labels(ds_dir / "cfg" / "content_label.txt")
        styles = _read_labels(ds_dir / "cfg" / "style_label.txt")
        for bvh in sorted((ds_dir / "data").glob("*.bvh")):
            stem = bvh.stem
            parts = stem.split("_")
            if len(parts) != 4:
                continue
            _, content, style, num = parts
            label_file = bvh.with_suffix(".json")
            if label_file.is_file():
                try:
                    lab = json.loads(label_file.read_text())
                    jc, js = contents[int(lab["content"])], styles[int(lab["style"])]
                except (ValueError, KeyError, IndexError, TypeError):
                    jc, js = content, style
                if (jc, js) != (content, style):
                    raise BuildError(f"{bvh}: file name says {content}/{style}, labels say {jc}/{js}")
            clips.append(Clip(f"b{ds}_{content}_{style}_{num}", bvh, ds, content, style))
    return clips


def _read_labels(path: Path) -> list[str]:
    if not path.is_file():
        raise BuildError(f"{path}: label file missing")
    return [re.sub(r"^dataset-\d+_", "", l.strip()) for l in path.read_text().splitlines() if l.strip()]


# ---------------------------------------------------------------- splits

def assign_splits(clips: list[Clip], seed: int = 0) -> dict[str, str]:
    """Stratify by (dataset, content, style): clips of each stratum are shuffled and laid
    end to end, and the run is dealt out along SPLIT_PATTERN, so every stratum and the
    whole set split about 80/5/15."""
    rng = np.random.default_rng(seed)
    strata = defaultdict(list)
    for c in clips:
        strata[(c.dataset, c.content, c.style)].append(c.name)
    order = []
    for key in sorted(strata):
        names = sorted(strata[key])
        rng.shuffle(names)
        order.extend(names)
    return {name: SPLIT_NAMES[SPLIT_PATTERN[i % len(SPLIT_PATTERN)]] for i, name in enumerate(order)}


# ---------------------------------------------------------------- conversion

def _load_worker(clip: Clip):
    import torch
    torch.set_num_threads(1)
    try:
        joints = load_bvh(clip.path, mapping="bandai", fps=rep.FPS).joints
    except BvhError as e:
        return clip.name, None, str(e)
    if len(joints) < MIN_FRAMES + 1:
        return clip.name, None, f"{clip.path}: too short ({len(joints)} frames at 20 fps, need {MIN_FRAMES + 1})"
    if not np.isfinite(joints).all():
        return clip.name, None, f"{clip.path}: non-finite joint positions"
    return clip.name, joints, None


def _convert_worker(args):
    import torch
    torch.set_num_threads(1)
    name, joints, lengths, out_dir = args
    joints = rep.canonicalize(rep.retarget(joints.astype(np.float64), lengths))
    for prefix, j in (("", joints), ("M", rep.mirror_joints(joints))):
        feats = rep.joints_to_features(j).astype(np.float32)
        recovered = rep.features_to_joints(feats).astype(np.float32)
        _atomic_save_npy(out_dir / "new_joints" / f"{prefix}{name}.npy", recovered)
        _atomic_save_npy(out_dir / "new_joint_vecs" / f"{prefix}{name}.npy", feats)
    return name


def build_bandai(source: str | Path, out: str | Path, workers: int = 2, seed: int = 0,
                 progress: bool = True) -> dict:
    source, out = Path(source), Path(out)
    if not source.exists():
        raise BuildError(f"{source}: no such file or directory")
    work = out.parent / f".{out.name}.building"
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (work / sub).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.unpack-") as unpack:
        root = source
        if source.is_file():
            if progress:
                tqdm.write(f"unpacking {source} ...")
            try:
                root = _unpack(source, Path(unpack))
            except (tarfile.TarError, OSError, EOFError) as e:
                raise BuildError(f"{source}: cannot read the archive ({e})") from None
        clips = discover_bandai(root)
        if not clips:
            raise BuildError(f"{source}: no Bandai-Namco-Research-Motiondataset-*/data/*.bvh clips found")

        skipped: dict[str, str] = {}
        loaded: dict[str, np.ndarray] = {}
        todo = [c for c in clips if not (work / "new_joint_vecs" / f"M{c.name}.npy").exists()]
        done_before = len(clips) - len(todo)
        # Pass 1: import every clip we still need (all of them when computing bone lengths).
        need_lengths = not (work / "skeleton.json").exists()
        to_load = clips if need_lengths else todo
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for name, joints, err in tqdm(pool.map(_load_worker, to_load, chunksize=8), total=len(to_load),
                                          desc="import BVH", disable=not progress):
                if err:
                    skipped[name] = err
                    tqdm.write(f"skipped: {err}")
                else:
                    loaded[name] = joints
        if need_lengths:
            lengths = np.median(np.stack([rep.bone_lengths(j) for j in loaded.values()]), axis=0)
            atomic_write_text(work / "skeleton.json", json.dumps(
                {"joint_names": list(rep.sk.JOINT_NAMES), "parents": rep.sk.PARENTS.tolist(),
                 "bone_lengths_m": [round(float(x), 5) for x in lengths]}, indent=2))
        lengths = np.array(json.loads((work / "skeleton.json").read_text())["bone_lengths_m"])

        # Pass 2: retarget, canonicalise, features, mirrors.
        jobs = [(c.name, loaded[c.name], lengths, work) for c in todo if c.name in loaded]
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for _ in tqdm(pool.map(_convert_worker, jobs, chunksize=4), total=len(jobs), desc="features",
                          disable=not progress):
                pass
        for c in clips:  # clips that failed in an earlier run are known by their missing output
            if c.name not in skipped and not (work / "new_joint_vecs" / f"M{c.name}.npy").exists():
                skipped[c.name] = f"{c.path}: conversion failed"

    good = [c for c in clips if c.name not in skipped]
    splits = assign_splits(good, seed)
    labels = {}
    for c in good:
        for prefix in ("", "M"):
            content = MIRRORED_CONTENT.get(c.content, c.content) if prefix else c.content
            caps = captions_for(content, c.style, f"{prefix}{c.name}", CAPTIONS_PER_CLIP)
            if prefix and content == c.content:
                caps = [swap_left_right(x) for x in caps]
            atomic_write_text(work / "texts" / f"{prefix}{c.name}.txt", "\n".join(caption_line(x) for x in caps) + "\n")
            labels[f"{prefix}{c.name}"] = {"dataset": c.dataset, "content": content, "style": c.style,
                                           "mirrored": bool(prefix), "source": f"{c.path.parent.parent.name}/data/{c.path.name}",
                                           "split": splits[c.name]}
    for split in ("train", "val", "test"):
        ids = sorted(n for n, lab in labels.items() if lab["split"] == split)
        atomic_write_text(work / f"{split}.txt", "\n".join(ids) + "\n")
    train = [np.load(work / "new_joint_vecs" / f"{n}.npy") for n, lab in sorted(labels.items()) if lab["split"] == "train"]
    mean, std = rep.feature_statistics(np.concatenate(train))
    _atomic_save_npy(work / "Mean.npy", mean)
    _atomic_save_npy(work / "Std.npy", std)
    atomic_write_text(work / "labels.json", json.dumps(labels, indent=1, sort_keys=True))
    report = {"source": str(source), "clips_found": len(clips), "clips_built": len(good),
              "clips_resumed": done_before, "motions_written": 2 * len(good),
              "skipped": dict(sorted(skipped.items())), "fps": rep.FPS, "seed": seed}
    atomic_write_text(work / "build_report.json", json.dumps(report, indent=2))

    # Swap the finished build into place.
    if out.exists():
        old = out.parent / f".{out.name}.old"
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
        os.replace(work, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(work, out)
    return report


# ---------------------------------------------------------------- statistics

def dataset_stats(root: str | Path) -> dict:
    """Counts per content, style and split, and the length distribution, of a built dataset
    (labels.json is optional: any HumanML3D-layout directory gives splits and lengths)."""
    root = Path(root)
    if not (root / "new_joint_vecs").is_dir():
        raise BuildError(f"{root}: not a HumanML3D-layout directory")
    labels = json.loads((root / "labels.json").read_text()) if (root / "labels.json").is_file() else {}
    splits = {}
    for s in ("train", "val", "test"):
        f = root / f"{s}.txt"
        if f.is_file():
            for n in f.read_text().split():
                splits[n] = s
    lengths = {}
    for f in sorted((root / "new_joint_vecs").glob("*.npy")):
        lengths[f.stem] = np.load(f, mmap_mode="r").shape[0]
    secs = np.array(list(lengths.values()), dtype=np.float64) / rep.FPS
    stats = {
        "motions": len(lengths),
        "per_split": dict(Counter(splits.get(n, "none") for n in lengths)),
        "per_content": dict(Counter(labels[n]["content"] for n in lengths if n in labels)),
        "per_style": dict(Counter(labels[n]["style"] for n in lengths if n in labels)),
        "hours": float(secs.sum() / 3600),
        "length_seconds": {q: float(np.percentile(secs, p)) for q, p in
                           (("min", 0), ("p10", 10), ("median", 50), ("p90", 90), ("max", 100))} if len(secs) else {},
    }
    edges = [0, 1, 2, 3, 4, 6, 8, 10, 15, 30, 1e9]
    hist = np.histogram(secs, bins=edges)[0]
    stats["length_histogram"] = {f"{a:g}-{b:g}s" if b < 1e9 else f">{a:g}s": int(h)
                                 for a, b, h in zip(edges[:-1], edges[1:], hist)}
    return stats
