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
leaves a half-written dataset; a rerun with the same sources resumes from the clips
already converted.

The steps every builder shares (start_build, convert_clips, finish_build) live here;
salad.data.build_bvh uses them for a folder of the user's own captioned BVH files.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tarfile
import tempfile
from collections import Counter, defaultdict
from collections.abc import Callable, Collection
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..eval.physics import net_turn_deg
from ..files import atomic_write_text
from ..motion import representation as rep
from ..motion.bvh import BvhError, load_bvh
from .captions import MIRRORED_CONTENT, caption_line, captions_for, swap_left_right
from ..files import atomic_write

SPLIT_PATTERN = "TTTXTTTTTTXTTTVTTXTT"   # 16 train, 1 val, 3 test in every 20 clips of a stratum run
SPLIT_NAMES = {"T": "train", "V": "val", "X": "test"}
MIN_FRAMES = 16                          # 0.8 s at 20 fps
CAPTIONS_PER_CLIP = 12  # varied verb phrases, word orders and manner words per motion (paraphrases understood)
# An action captured only in styles (no "normal" take, e.g. walk-back once its cut-off take is dropped) gives this
# many of each take's captions without a manner word, so a prompt that names none still has examples.
PLAIN_CAPTIONS = 3
# A take under this share of the median length of its action's takes (with at least CUT_OFF_MIN_TAKES
# of them to take a median over) was cut off early: the only unstyled walk-back take is 1 s where the
# styled ones run 6-13 s, and trained on, it taught the plain "walks backward" prompt a 1 s motion.
CUT_OFF_SHARE = 0.25
CUT_OFF_MIN_TAKES = 4
# A walk-turn take must turn the way its action names by at least this much. A few of dataset 2's takes turn
# the other way or barely at all (its walk-turn-right masculine_006 turns 260° to the left); trained on, they
# teach "turns right" a left turn, and one of them sat among the test clips the fidelity benchmark measures.
TURN_AGREES_DEG = 45.0


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
    atomic_write(path, lambda f: np.save(f, array))


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

def assign_splits(clips: list[Clip], seed: int = 0, dropped: Collection[str] = ()) -> dict[str, str]:
    """Stratify by (dataset, content, style): clips of each stratum are shuffled and laid
    end to end, and the run is dealt out along SPLIT_PATTERN, so every stratum and the
    whole set split about 80/5/15. A content class the dealing leaves without a training
    clip (one recorded once, such as Bandai's kick) gets its first clip back in train: a
    model cannot learn an action it never sees, and one held-out clip measures nothing.
    Clips named in `dropped` keep their place in the dealing and are then left out, so
    dropping a clip moves no other clip between splits."""
    rng = np.random.default_rng(seed)
    strata = defaultdict(list)
    for c in clips:
        strata[(c.dataset, c.content, c.style)].append(c.name)
    order = []
    for key in sorted(strata):
        names = sorted(strata[key])
        rng.shuffle(names)
        order.extend(names)
    gone = set(dropped)
    splits = {name: SPLIT_NAMES[SPLIT_PATTERN[i % len(SPLIT_PATTERN)]] for i, name in enumerate(order)
              if name not in gone}
    order = [n for n in order if n not in gone]
    content = {c.name: c.content for c in clips}
    first = {}
    for name in order:
        first.setdefault(content[name], name)
    trained = {content[n] for n, s in splits.items() if s == "train"}
    for cls, name in first.items():
        if cls not in trained:
            splits[name] = "train"
    return splits


# ---------------------------------------------------------------- the shared pipeline
#
# Every builder goes: find clips -> start_build -> convert_clips -> captions and splits of
# its own -> finish_build. Only the discovery, the captions and the split rule differ.

SETTINGS_FILE = ".settings.json"   # what the hidden build was started with; resumed only if it matches
IMPORTS_FILE = ".imports.json"     # clip -> joint mapping that imported it, kept across resumed runs


def check_output(source: Path, out: Path) -> None:
    """Refuse outputs that the final swap would destroy: the input itself, a folder holding
    the input, or an existing folder that is not an earlier build."""
    src, dst = source.resolve(), out.resolve()
    if src == dst or dst in src.parents:
        raise BuildError(f"{out}: the output would replace the input {source}; choose another folder")
    if dst.is_file() or (dst.is_dir() and any(dst.iterdir()) and not (dst / "build_report.json").is_file()):
        raise BuildError(f"{out}: exists and is not an earlier build (no build_report.json); "
                         f"it would be replaced, so choose a new or empty folder")


def start_build(out: Path, settings: dict) -> Path:
    """The hidden work directory `.<out>.building` next to `out`. A leftover from an
    interrupted build with the same settings is resumed; any other leftover is cleared."""
    settings = json.loads(json.dumps(settings))  # tuples become lists, as they will read back
    work = out.parent / f".{out.name}.building"
    stamp = work / SETTINGS_FILE
    if work.exists():
        try:
            same = json.loads(stamp.read_text()) == settings
        except (OSError, ValueError):
            same = False
        if not same:
            shutil.rmtree(work)
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (work / sub).mkdir(parents=True, exist_ok=True)
    atomic_write_text(stamp, json.dumps(settings))
    return work


def source_fingerprint(sources: dict[str, Path]) -> list:
    """Name, size and modification time of every source file: any change restarts a resumed build,
    because the shared skeleton is the median over all clips."""
    return [[name, st.st_size, st.st_mtime_ns] for name, st in
            ((name, path.stat()) for name, path in sorted(sources.items()))]


@dataclass
class Conversion:
    built: list[str]              # clips whose features are on disk, in input order
    skipped: dict[str, str]       # clip -> why not
    resumed: int                  # clips already converted by an interrupted run
    mappings: dict[str, str]      # clip -> joint mapping that imported it


def _load_worker(job):
    import torch
    torch.set_num_threads(1)
    name, path, mapping = job
    try:
        clip = load_bvh(path, mapping=mapping, fps=rep.FPS)
    except BvhError as e:
        return name, None, str(e), None
    joints = clip.joints
    if len(joints) < MIN_FRAMES + 1:
        return name, None, f"{path}: too short ({len(joints)} frames at 20 fps, need {MIN_FRAMES + 1})", None
    if not np.isfinite(joints).all():
        return name, None, f"{path}: non-finite joint positions", None
    return name, joints, None, clip.mapping_name


def _convert_worker(job):
    import torch
    torch.set_num_threads(1)
    name, joints, lengths, out_dir, mirror, path = job
    try:
        joints = rep.canonicalize(rep.retarget(joints.astype(np.float64), lengths))
        versions = (("", joints), ("M", rep.mirror_joints(joints))) if mirror else (("", joints),)
        results = []
        for prefix, j in versions:
            feats = rep.joints_to_features(j).astype(np.float32)
            if not np.isfinite(feats).all():
                return name, f"{path}: non-finite features (degenerate skeleton?)"
            results.append((prefix, feats, rep.features_to_joints(feats).astype(np.float32)))
    except (ValueError, RuntimeError) as e:
        return name, f"{path}: conversion failed ({e})"
    # The features file of the last version is written last: its presence marks the clip done.
    for prefix, feats, recovered in results:
        _atomic_save_npy(out_dir / "new_joints" / f"{prefix}{name}.npy", recovered)
        _atomic_save_npy(out_dir / "new_joint_vecs" / f"{prefix}{name}.npy", feats)
    return name, None


def convert_clips(sources: dict[str, Path], work: Path, mapping="auto", mirror: bool = True,
                  workers: int = 2, progress: bool = True) -> Conversion:
    """Import BVH clips {name: path}, retarget them onto one skeleton (the median bone lengths of the
    set, saved as skeleton.json), canonicalise and write features, joints and optional mirrors (M<name>)."""
    def done(name: str) -> bool:
        return (work / "new_joint_vecs" / f"{'M' if mirror else ''}{name}.npy").exists()

    todo = [n for n in sources if not done(n)]
    skipped: dict[str, str] = {}
    loaded: dict[str, np.ndarray] = {}
    imports_path = work / IMPORTS_FILE
    mappings = json.loads(imports_path.read_text()) if imports_path.exists() else {}
    # Pass 1: import every clip still needed (all of them while the bone lengths are unknown).
    need_lengths = not (work / "skeleton.json").exists()
    to_load = list(sources) if need_lengths else todo
    jobs = [(n, sources[n], mapping) for n in to_load]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for name, joints, err, used in tqdm(pool.map(_load_worker, jobs, chunksize=8), total=len(jobs),
                                            desc="import BVH", disable=not progress):
            if err:
                skipped[name] = err
                if progress:
                    tqdm.write(f"skipped: {err}")
            else:
                loaded[name] = joints
                mappings[name] = used
    atomic_write_text(imports_path, json.dumps(mappings))
    if need_lengths:
        if not loaded:
            return Conversion([], skipped, 0, {})
        lengths = np.median(np.stack([rep.bone_lengths(j) for j in loaded.values()]), axis=0)
        atomic_write_text(work / "skeleton.json", json.dumps(
            {"joint_names": list(rep.sk.JOINT_NAMES), "parents": rep.sk.PARENTS.tolist(),
             "bone_lengths_m": [round(float(x), 5) for x in lengths]}, indent=2))
    lengths = np.array(json.loads((work / "skeleton.json").read_text())["bone_lengths_m"])

    # Pass 2: retarget, canonicalise, features, mirrors.
    jobs = [(n, loaded[n], lengths, work, mirror, sources[n]) for n in todo if n in loaded]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for name, err in tqdm(pool.map(_convert_worker, jobs, chunksize=4), total=len(jobs), desc="features",
                              disable=not progress):
            if err:
                skipped[name] = err
                if progress:
                    tqdm.write(f"skipped: {err}")
    for n in sources:  # clips that failed in an earlier run are known by their missing output
        if n not in skipped and not done(n):
            skipped[n] = f"{sources[n]}: conversion failed"
    built = [n for n in sources if n not in skipped]
    return Conversion(built, skipped, len(sources) - len(todo), {n: mappings.get(n, "") for n in built})


def finish_build(work: Path, out: Path, texts: dict[str, list[str]], splits: dict[str, str], report: dict,
                 extra_json: dict[str, dict] | None = None) -> dict:
    """Write captions (texts/<id>.txt, lines in HumanML3D's format), split lists, train
    statistics, extra JSON files and build_report.json, then swap the build into place."""
    for name, lines in texts.items():
        atomic_write_text(work / "texts" / f"{name}.txt", "".join(line + "\n" for line in lines))
    for split in ("train", "val", "test"):
        ids = sorted(n for n, s in splits.items() if s == split)
        atomic_write_text(work / f"{split}.txt", "\n".join(ids) + "\n")
    train = sorted(n for n, s in splits.items() if s == "train")
    if not train:
        raise BuildError(f"{out}: no motion landed in the training split")
    mean, std = rep.feature_statistics(np.concatenate([np.load(work / "new_joint_vecs" / f"{n}.npy") for n in train]))
    _atomic_save_npy(work / "Mean.npy", mean)
    _atomic_save_npy(work / "Std.npy", std)
    for file_name, doc in (extra_json or {}).items():
        atomic_write_text(work / file_name, json.dumps(doc, indent=1, sort_keys=True))
    atomic_write_text(work / "build_report.json", json.dumps(report, indent=2))
    for f in (SETTINGS_FILE, IMPORTS_FILE):
        (work / f).unlink(missing_ok=True)

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


def cut_off_takes(clips: list[Clip], frames: dict[str, int]) -> dict[str, str]:
    """Clips (name -> why) far shorter than the other takes of their action (CUT_OFF_SHARE)."""
    by_content: dict[str, list[int]] = defaultdict(list)
    for c in clips:
        by_content[c.content].append(frames[c.name])
    out = {}
    for c in clips:
        takes = by_content[c.content]
        median = float(np.median(takes))
        if len(takes) >= CUT_OFF_MIN_TAKES and frames[c.name] < CUT_OFF_SHARE * median:
            out[c.name] = (f"{c.path}: cut off ({frames[c.name]} frames where the {len(takes)} takes of "
                           f"{c.content} have a median of {median:.0f})")
    return out


def contrary_turns(clips: list[Clip], joints: Callable[[str], np.ndarray]) -> dict[str, str]:
    """Walk-turn takes (name -> why) that do not turn at least TURN_AGREES_DEG the way their action says."""
    out = {}
    for c in clips:
        side = {"walk-turn-left": 1.0, "walk-turn-right": -1.0}.get(c.content)
        if side is None:
            continue
        turn = net_turn_deg(joints(c.name))
        if side * turn < TURN_AGREES_DEG:
            way = "to the left" if turn > 0 else "to the right"
            out[c.name] = f"{c.path}: turns {abs(turn):.0f}° {way}, against its action {c.content}"
    return out


# ---------------------------------------------------------------- Bandai

def build_bandai(source: str | Path, out: str | Path, workers: int = 2, seed: int = 0,
                 progress: bool = True) -> dict:
    """Build the dataset from the Bandai-Namco archive (.tar.xz) or its unpacked folder."""
    source, out = Path(source), Path(out)
    if not source.exists():
        raise BuildError(f"{source}: no such file or directory")
    check_output(source, out)
    out.parent.mkdir(parents=True, exist_ok=True)
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
        sources = {c.name: c.path for c in clips}
        work = start_build(out, {"builder": "bandai", "clips": source_fingerprint(sources)})
        conv = convert_clips(sources, work, mapping="bandai", mirror=True, workers=workers, progress=progress)

    def shown(why: str) -> str:
        # the unpacked copy is gone by now: name a clip by its place in the archive
        return why.replace(f"{unpack}{os.sep}", f"{source.name}:") if root != source else why

    good = [c for c in clips if c.name not in conv.skipped]
    if not good:
        shutil.rmtree(work, ignore_errors=True)  # nothing worth resuming
        raise BuildError(f"{source}: no clip could be imported; first problems: "
                         + "; ".join(shown(why) for why in list(conv.skipped.values())[:3]))
    cut = cut_off_takes(good, {c.name: np.load(work / "new_joint_vecs" / f"{c.name}.npy", mmap_mode="r").shape[0]
                               for c in good})
    cut.update(contrary_turns(good, lambda name: np.load(work / "new_joints" / f"{name}.npy")))
    for name in cut:
        for sub in ("new_joint_vecs", "new_joints"):
            for prefix in ("", "M"):
                (work / sub / f"{prefix}{name}.npy").unlink(missing_ok=True)
    conv.skipped.update(cut)
    splits = assign_splits(good, seed, dropped=cut)
    good = [c for c in good if c.name not in cut]
    labels, texts = {}, {}
    styled_only = {c.content for c in good} - {c.content for c in good if c.style == "normal"}
    for c in good:
        for prefix in ("", "M"):
            content = MIRRORED_CONTENT.get(c.content, c.content) if prefix else c.content
            caps = captions_for(content, c.style, f"{prefix}{c.name}", CAPTIONS_PER_CLIP)
            if c.content in styled_only:
                caps = caps[:-PLAIN_CAPTIONS] + captions_for(content, c.style, f"{prefix}{c.name}/plain",
                                                             PLAIN_CAPTIONS, plain=True)
            if prefix and content == c.content:
                caps = [swap_left_right(x) for x in caps]
            texts[f"{prefix}{c.name}"] = [caption_line(x) for x in caps]
            labels[f"{prefix}{c.name}"] = {"dataset": c.dataset, "content": content, "style": c.style,
                                           "mirrored": bool(prefix), "source": f"{c.path.parent.parent.name}/data/{c.path.name}",
                                           "split": splits[c.name]}
    report = {"source": str(source), "clips_found": len(clips), "clips_built": len(good),
              "clips_resumed": conv.resumed, "motions_written": 2 * len(good),
              "skipped": {n: shown(why) for n, why in sorted(conv.skipped.items())}, "fps": rep.FPS, "seed": seed}
    return finish_build(work, out, texts, {n: lab["split"] for n, lab in labels.items()}, report,
                        {"labels.json": labels})


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
