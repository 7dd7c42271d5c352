"""Reading BVH files: the hierarchy, the MOTION block, and forward kinematics.

Any skeleton, any number and order of channels per joint. Position channels,
where a joint has them, replace the matching components of its OFFSET (the
usual reading, and what the Bandai-Namco files need: every joint carries six
channels there). Rotation channels compose outermost first, so `Zrotation
Xrotation Yrotation` means R = Rz @ Rx @ Ry, in degrees.

The MOTION block is parsed in one call to NumPy's C number parser, and forward
kinematics runs as batched matrix products per joint over all frames at once.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from .quaternion import euler_to_matrix


class BvhError(ValueError):
    """A BVH file or text that cannot be read; the message names the source and the reason."""


_CHANNEL_NAMES = {
    f"{axis}{kind}".lower(): f"{axis}{kind}"
    for axis in "XYZ" for kind in ("position", "rotation")
}
_MOTION_HEADER = re.compile(
    r"MOTION\s+Frames\s*:\s*(\S+)\s+Frame\s+Time\s*:\s*(\S+)[ \t]*", re.IGNORECASE)


@dataclass
class BvhData:
    """A parsed BVH file: joints in file order (parents before children) and raw channel data."""

    names: tuple[str, ...]
    parents: np.ndarray                      # (J,) int, -1 for roots
    offsets: np.ndarray                      # (J, 3) float64, file units
    channels: tuple[tuple[str, ...], ...]    # per joint, e.g. ("Xposition", ..., "Yrotation")
    frame_time: float                        # seconds
    motion: np.ndarray                       # (T, sum of channel counts) float64
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint index -> offset
    source: str = "<text>"

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def channel_starts(self) -> np.ndarray:
        """Column of each joint's first channel in `motion`."""
        counts = np.array([len(c) for c in self.channels], dtype=np.int64)
        return np.concatenate(([0], np.cumsum(counts)[:-1]))

    def joint_index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise BvhError(f"{self.source}: no joint named {name!r}") from None

    def global_positions(self, joints: Iterable[int] | None = None) -> np.ndarray:
        """World positions (T, len(joints), 3) in file units of the given joint indices (all by default).

        Only the selected joints and their ancestors are evaluated.
        """
        wanted = list(range(len(self.names))) if joints is None else [int(j) for j in joints]
        needed = np.zeros(len(self.names), dtype=bool)
        needs_rotation = np.zeros(len(self.names), dtype=bool)
        for j in wanted:
            needed[j] = True
            p = self.parents[j]
            while p >= 0:
                needed[p] = needs_rotation[p] = True
                p = self.parents[p]

        motion = torch.from_numpy(self.motion)
        T = self.num_frames
        starts = self.channel_starts
        pos: dict[int, torch.Tensor] = {}
        rot: dict[int, torch.Tensor] = {}
        for j in np.flatnonzero(needed):
            local = torch.from_numpy(self.offsets[j]).expand(T, 3).clone()
            order = ""
            rot_cols = []
            for k, ch in enumerate(self.channels[j]):
                col = starts[j] + k
                axis = "XYZ".index(ch[0])
                if ch.endswith("position"):
                    local[:, axis] = motion[:, col]
                else:
                    order += ch[0]
                    rot_cols.append(col)
            p = int(self.parents[j])
            # A missing entry in `rot` stands for the identity (no rotation channels up the chain).
            parent_rot = rot.get(p)
            if p < 0:
                pos[j] = local
            elif parent_rot is None:
                pos[j] = pos[p] + local
            else:
                pos[j] = pos[p] + (parent_rot @ local.unsqueeze(-1)).squeeze(-1)
            if not needs_rotation[j]:
                continue
            if order:
                local_rot = euler_to_matrix(torch.deg2rad(motion[:, rot_cols]), order)
                rot[j] = local_rot if parent_rot is None else parent_rot @ local_rot
            elif parent_rot is not None:
                rot[j] = parent_rot
        return torch.stack([pos[j] for j in wanted], dim=1).numpy()


# ---------------------------------------------------------------- reading

def read_bvh_text(path: str | os.PathLike) -> str:
    """The text of a BVH file; BvhError if it is missing or unreadable."""
    name = str(path)
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise BvhError(f"{name}: file not found") from None
    except IsADirectoryError:
        raise BvhError(f"{name}: is a directory, not a BVH file") from None
    except OSError as e:
        raise BvhError(f"{name}: cannot read ({e.strerror or e})") from None
    if b"\0" in raw[:4096]:
        raise BvhError(f"{name}: not a BVH file (binary data)")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        # Joint names in some exporters' files are in a legacy code page.
        return raw.decode("latin-1")


def parse_bvh(source: str | os.PathLike) -> BvhData:
    """Parse a BVH file (a path, or a str without newlines naming one) or BVH text (a str with newlines)."""
    if isinstance(source, str) and "\n" in source:
        text, name = source, "<text>"
    else:
        text, name = read_bvh_text(source), str(source)
    return parse_bvh_text(text, name)


def parse_bvh_text(text: str, name: str = "<text>") -> BvhData:
    """Parse BVH text; `name` is used in error messages."""
    m = re.search(r"^\s*MOTION\b", text, re.IGNORECASE | re.MULTILINE)
    head = text if m is None else text[:m.start()]
    names, parents, offsets, channels, end_sites = _parse_hierarchy(head, name)
    if m is None:
        raise BvhError(f"{name}: no MOTION section (file truncated?)")
    frame_time, motion = _parse_motion(text[m.start():], sum(len(c) for c in channels), name)
    return BvhData(
        names=tuple(names), parents=np.array(parents, dtype=np.int64),
        offsets=np.array(offsets, dtype=np.float64).reshape(-1, 3),
        channels=tuple(channels), frame_time=frame_time, motion=motion,
        end_sites=end_sites, source=name,
    )


def _floats(tokens: list[str], name: str, what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise BvhError(f"{name}: {what} has a non-numeric value in {' '.join(tokens)!r}") from None
    if not all(np.isfinite(values)):
        raise BvhError(f"{name}: {what} is not finite: {' '.join(tokens)!r}")
    return values


def _parse_hierarchy(head: str, name: str):
    tokens = head.split()
    if not tokens or tokens[0].upper() != "HIERARCHY":
        raise BvhError(f"{name}: not a BVH file (does not start with HIERARCHY)")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float] | None] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []
    n = len(tokens)
    i = 1

    def need(count: int, what: str) -> list[str]:
        if i + count > n:
            raise BvhError(f"{name}: HIERARCHY ends inside {what} (file truncated?)")
        return tokens[i:i + count]

    while i < n:
        tok = tokens[i]
        key = tok.upper()
        current = names[stack[-1]] if stack else None
        if key in ("ROOT", "JOINT"):
            if key == "JOINT" and not stack:
                raise BvhError(f"{name}: JOINT outside any ROOT")
            if key == "ROOT" and stack:
                raise BvhError(f"{name}: ROOT nested inside joint {current!r}")
            # A name runs up to the brace, so names with spaces survive.
            j = i + 1
            while j < n and tokens[j] != "{":
                j += 1
            if j >= n or j == i + 1:
                raise BvhError(f"{name}: {tok} without a name and '{{' (after joint {current!r})")
            joint = " ".join(tokens[i + 1:j])
            if joint in names:
                raise BvhError(f"{name}: joint name {joint!r} appears twice")
            names.append(joint)
            parents.append(stack[-1] if stack else -1)
            offsets.append(None)
            channels.append(())
            stack.append(len(names) - 1)
            i = j + 1
        elif key == "END":
            if not stack:
                raise BvhError(f"{name}: End Site outside any joint")
            block = need(8, f"the End Site of {current!r}")
            if block[1].upper() != "SITE" or block[2] != "{" or block[3].upper() != "OFFSET" or block[7] != "}":
                raise BvhError(f"{name}: malformed End Site in joint {current!r}")
            end_sites[stack[-1]] = np.array(_floats(block[4:7], name, f"End Site OFFSET of {current!r}"))
            i += 8
        elif key == "OFFSET":
            if not stack:
                raise BvhError(f"{name}: OFFSET outside any joint")
            offsets[stack[-1]] = _floats(need(4, f"OFFSET of {current!r}")[1:], name, f"OFFSET of {current!r}")
            i += 4
        elif key == "CHANNELS":
            if not stack:
                raise BvhError(f"{name}: CHANNELS outside any joint")
            count_tok = need(2, f"CHANNELS of {current!r}")[1]
            if not count_tok.isdigit():
                raise BvhError(f"{name}: CHANNELS count {count_tok!r} of joint {current!r} is not a number")
            count = int(count_tok)
            raw = need(2 + count, f"CHANNELS of {current!r}")[2:]
            chans = []
            for c in raw:
                if c.lower() not in _CHANNEL_NAMES:
                    raise BvhError(f"{name}: unknown channel {c!r} in joint {current!r}")
                chans.append(_CHANNEL_NAMES[c.lower()])
            if len(set(chans)) != len(chans):
                raise BvhError(f"{name}: joint {current!r} lists a channel twice: {' '.join(raw)}")
            channels[stack[-1]] = tuple(chans)
            i += 2 + count
        elif tok == "}":
            if not stack:
                raise BvhError(f"{name}: unbalanced '}}' in HIERARCHY")
            stack.pop()
            i += 1
        else:
            where = f"in joint {current!r}" if current else "in HIERARCHY"
            raise BvhError(f"{name}: unexpected {tok!r} {where}")
    if stack:
        raise BvhError(f"{name}: HIERARCHY ends inside joint {names[stack[-1]]!r} (file truncated?)")
    if not names:
        raise BvhError(f"{name}: HIERARCHY has no joints")
    for j, off in enumerate(offsets):
        if off is None:
            raise BvhError(f"{name}: joint {names[j]!r} has no OFFSET")
    return names, parents, offsets, channels, end_sites


def _parse_motion(section: str, num_channels: int, name: str) -> tuple[float, np.ndarray]:
    m = _MOTION_HEADER.match(section)
    if m is None:
        raise BvhError(f"{name}: MOTION section lacks 'Frames:' and 'Frame Time:' lines")
    frames_tok, time_tok = m.groups()
    if not frames_tok.isdigit():
        raise BvhError(f"{name}: 'Frames: {frames_tok}' is not a frame count")
    frames = int(frames_tok)
    try:
        frame_time = float(time_tok)
    except ValueError:
        raise BvhError(f"{name}: 'Frame Time: {time_tok}' is not a number") from None
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise BvhError(f"{name}: Frame Time must be positive, got {time_tok}")
    if frames == 0:
        raise BvhError(f"{name}: MOTION has zero frames")
    if num_channels == 0:
        raise BvhError(f"{name}: the skeleton declares no channels, so there is no motion to read")
    body = section[m.end():]
    try:
        values = np.fromstring(body, dtype=np.float64, sep=" ")
    except ValueError:
        bad = next((t for t in body.split() if not _is_number(t)), "?")
        raise BvhError(f"{name}: MOTION data has a non-numeric value {bad!r}") from None
    expected = frames * num_channels
    if values.size != expected:
        raise BvhError(f"{name}: {_describe_shape_mismatch(body, frames, num_channels, values.size)}")
    motion = values.reshape(frames, num_channels)
    finite = np.isfinite(motion)
    if not finite.all():
        row, col = np.argwhere(~finite)[0]
        raise BvhError(f"{name}: MOTION data holds {motion[row, col]} (frame {row}, channel {col})")
    return frame_time, motion


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _describe_shape_mismatch(body: str, frames: int, num_channels: int, got: int) -> str:
    """Explain why the MOTION block does not hold frames x channels values (error path only)."""
    rows = [line.split() for line in body.splitlines() if line.strip()]
    for k, row in enumerate(rows):
        if len(row) != num_channels and (k < len(rows) - 1 or len(row) > num_channels):
            return (f"MOTION frame {k} has {len(row)} values but the skeleton has "
                    f"{num_channels} channels")
    if rows and len(rows[-1]) < num_channels:
        return (f"MOTION data is truncated: frame {len(rows) - 1} has {len(rows[-1])} of "
                f"{num_channels} values (header says {frames} frames)")
    if len(rows) < frames:
        return f"MOTION data is truncated: header says {frames} frames, found {len(rows)}"
    return f"MOTION data has {len(rows)} frames but the header says {frames}"
