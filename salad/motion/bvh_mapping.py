"""Name tables that map a BVH skeleton's joints onto the 22 HumanML3D joints.

A table maps each of the 22 target names (skeleton.JOINT_NAMES) to a source
joint name, or to a blend ``(a, b, t)`` meaning the point ``a + t * (b - a)``
between two source joints. Source names are matched exactly first, then
ignoring case and any ``namespace:`` prefix, so ``mixamorig1:LeftArm`` and
``Left_hip`` resolve too.
"""
from __future__ import annotations

from typing import Mapping, Union

import numpy as np

from . import skeleton as sk
from .bvh_parse import BvhData, BvhError

MappingEntry = Union[str, tuple[str, str, float]]
JointMapping = Mapping[str, MappingEntry]


def _sided(template: dict[str, str], left: str, right: str) -> dict[str, str]:
    out = {}
    for target, src in template.items():
        if "{side}" in target:
            out[target.format(side="left")] = src.format(side=left)
            out[target.format(side="right")] = src.format(side=right)
        else:
            out[target] = src
    return out


def _ordered(table: dict[str, MappingEntry]) -> dict[str, MappingEntry]:
    return {name: table[name] for name in sk.JOINT_NAMES}


# Bandai-Namco-Research-Motiondataset: centimetres, character's left +X, forward +Z.
BANDAI_MAPPING: dict[str, MappingEntry] = _ordered({
    **_sided({
        "{side}_hip": "UpperLeg_{side}", "{side}_knee": "LowerLeg_{side}",
        "{side}_ankle": "Foot_{side}", "{side}_foot": "Toes_{side}",
        "{side}_collar": "Shoulder_{side}", "{side}_shoulder": "UpperArm_{side}",
        "{side}_elbow": "LowerArm_{side}", "{side}_wrist": "Hand_{side}",
    }, "L", "R"),
    "pelvis": "Hips",
    # The Bandai spine has two segments where SMPL has three.
    "spine1": ("Hips", "Spine", 0.6),
    "spine2": ("Spine", "Chest", 0.5),
    "spine3": "Chest",
    "neck": "Neck",
    "head": "Head",
})

# What save_bvh writes: the project's own joint names.
SALAD_MAPPING: dict[str, MappingEntry] = {name: name for name in sk.JOINT_NAMES}

SMPL_MAPPING: dict[str, MappingEntry] = _ordered({
    **_sided({
        "{side}_hip": "{side}_Hip", "{side}_knee": "{side}_Knee", "{side}_ankle": "{side}_Ankle",
        "{side}_foot": "{side}_Foot", "{side}_collar": "{side}_Collar",
        "{side}_shoulder": "{side}_Shoulder", "{side}_elbow": "{side}_Elbow",
        "{side}_wrist": "{side}_Wrist",
    }, "L", "R"),
    "pelvis": "Pelvis", "spine1": "Spine1", "spine2": "Spine2", "spine3": "Spine3",
    "neck": "Neck", "head": "Head",
})

MIXAMO_MAPPING: dict[str, MappingEntry] = _ordered({
    **_sided({
        "{side}_hip": "mixamorig:{side}UpLeg", "{side}_knee": "mixamorig:{side}Leg",
        "{side}_ankle": "mixamorig:{side}Foot", "{side}_foot": "mixamorig:{side}ToeBase",
        "{side}_collar": "mixamorig:{side}Shoulder", "{side}_shoulder": "mixamorig:{side}Arm",
        "{side}_elbow": "mixamorig:{side}ForeArm", "{side}_wrist": "mixamorig:{side}Hand",
    }, "Left", "Right"),
    "pelvis": "mixamorig:Hips", "spine1": "mixamorig:Spine", "spine2": "mixamorig:Spine1",
    "spine3": "mixamorig:Spine2", "neck": "mixamorig:Neck", "head": "mixamorig:Head",
})

# Tried in this order by mapping="auto". The lower-case project names also match
# the "Left_hip"/"Right_knee" spelling of several SMPL-to-BVH exporters.
MAPPINGS: dict[str, dict[str, MappingEntry]] = {
    "bandai": BANDAI_MAPPING,
    "salad": SALAD_MAPPING,
    "smpl": SMPL_MAPPING,
    "mixamo": MIXAMO_MAPPING,
}


def _normalise(name: str) -> str:
    return name.rsplit(":", 1)[-1].strip().casefold()


def source_names(entry: MappingEntry) -> tuple[str, ...]:
    return (entry,) if isinstance(entry, str) else (entry[0], entry[1])


class _NameIndex:
    """Finds source joints by exact name, else by normalised name when that is unambiguous."""

    def __init__(self, names: tuple[str, ...]):
        self.exact = {n: i for i, n in enumerate(names)}
        self.loose: dict[str, int | None] = {}
        for i, n in enumerate(names):
            key = _normalise(n)
            self.loose[key] = None if key in self.loose else i

    def find(self, name: str) -> int | None:
        if name in self.exact:
            return self.exact[name]
        return self.loose.get(_normalise(name))


def validate_mapping(mapping: JointMapping, where: str = "mapping") -> dict[str, MappingEntry]:
    """Check a user table: all 22 targets, each a name or (name, name, weight)."""
    if not isinstance(mapping, Mapping):
        raise BvhError(f"{where}: a mapping must be a dict or one of {sorted(MAPPINGS)} or 'auto'")
    unknown = sorted(set(mapping) - set(sk.JOINT_NAMES))
    missing = [n for n in sk.JOINT_NAMES if n not in mapping]
    if unknown or missing:
        raise BvhError(f"{where}: mapping keys must be the 22 joint names; "
                       f"unknown {unknown}, missing {missing}")
    out: dict[str, MappingEntry] = {}
    for target in sk.JOINT_NAMES:
        entry = mapping[target]
        if isinstance(entry, str):
            out[target] = entry
        elif (isinstance(entry, (tuple, list)) and len(entry) == 3 and isinstance(entry[0], str)
              and isinstance(entry[1], str) and isinstance(entry[2], (int, float))
              and np.isfinite(entry[2])):
            out[target] = (entry[0], entry[1], float(entry[2]))
        else:
            raise BvhError(f"{where}: entry for {target!r} must be a joint name or "
                           f"(name, name, weight), got {entry!r}")
    return out


def _missing(table: JointMapping, index: _NameIndex) -> list[str]:
    names = dict.fromkeys(n for e in table.values() for n in source_names(e))
    return [n for n in names if index.find(n) is None]


def resolve_mapping(data: BvhData, mapping: str | JointMapping = "auto"
                    ) -> tuple[str, dict[str, MappingEntry]]:
    """(name, table) of the mapping to use for this file; BvhError naming missing joints."""
    index = _NameIndex(data.names)
    if isinstance(mapping, str):
        if mapping == "auto":
            candidates = list(MAPPINGS.items())
        elif mapping in MAPPINGS:
            candidates = [(mapping, MAPPINGS[mapping])]
        else:
            raise BvhError(f"{data.source}: unknown mapping {mapping!r}; "
                           f"use 'auto', one of {sorted(MAPPINGS)}, or a dict")
    else:
        candidates = [("custom", validate_mapping(mapping, data.source))]
    misses = []
    for name, table in candidates:
        missing = _missing(table, index)
        if not missing:
            return name, dict(table)
        misses.append((len(missing), name, missing))
    misses.sort(key=lambda m: m[0])
    detail = "; ".join(f"{name!r} lacks {', '.join(missing)}" for _, name, missing in misses)
    raise BvhError(f"{data.source}: joint names do not match "
                   f"{'any built-in mapping' if mapping == 'auto' else 'the mapping'}: {detail}")


def mapped_positions(data: BvhData, table: dict[str, MappingEntry]) -> np.ndarray:
    """(T, 22, 3) positions in file units of the 22 target joints under a resolved table."""
    index = _NameIndex(data.names)
    sources = list(dict.fromkeys(index.find(n) for e in table.values() for n in source_names(e)))
    column = {j: k for k, j in enumerate(sources)}
    pos = data.global_positions(sources)
    out = np.empty((pos.shape[0], sk.NUM_JOINTS, 3), dtype=np.float64)
    for t, target in enumerate(sk.JOINT_NAMES):
        entry = table[target]
        if isinstance(entry, str):
            out[:, t] = pos[:, column[index.find(entry)]]
        else:
            a = pos[:, column[index.find(entry[0])]]
            b = pos[:, column[index.find(entry[1])]]
            out[:, t] = a + entry[2] * (b - a)
    return out
