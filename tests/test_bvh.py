"""BVH import and export: parsing, forward kinematics, name mapping, units, resampling,
malformed input, round trips (our reader, bvhio, and Blender where installed), and real
Bandai-Namco clips."""
import json
import math
import os
import shutil
import subprocess
import tarfile

import numpy as np
import pytest
import torch

from conftest import synthetic_walk
from salad.cli import build_parser
from salad.motion import representation as rep
from salad.motion import skeleton as sk
from salad.motion.bvh import (
    BANDAI_MAPPING, MAPPINGS, UNITS_PER_METRE, BvhClip, BvhError, bvh_text, detect_scale, load_bvh,
    parse_bvh, resample, save_bvh,
)
from salad.motion.bvh_export import local_rotations, rest_offsets
from salad.motion.motion import Motion


def rx(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


ARM = """HIERARCHY
ROOT hips
{
  OFFSET 100 200 300
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT upper
  {
    OFFSET 0 10 0
    CHANNELS 3 %s
    JOINT lower
    {
      OFFSET 0 0 5
      CHANNELS 2 Yrotation Xrotation
      End Site
      {
        OFFSET 0 0 1
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3 0 0 0 0 0 0 0 0
1 2 3 90 0 0 %s 0 90
"""


def write(tmp_path, text, name="clip.bvh"):
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------- parsing and forward kinematics

def test_forward_kinematics_of_a_tiny_skeleton_matches_the_hand_computed_answer():
    data = parse_bvh(ARM % ("Zrotation Xrotation Yrotation", "0 0 0"))
    assert data.names == ("hips", "upper", "lower")
    assert list(data.parents) == [-1, 0, 1]
    assert data.num_frames == 2 and data.frame_time == 0.5
    assert np.allclose(data.end_sites[2], [0, 0, 1])
    pos = data.global_positions()
    # Frame 0: the root position channels replace the root OFFSET.
    assert np.allclose(pos[0], [[1, 2, 3], [1, 12, 3], [1, 12, 8]])
    # Frame 1: root turns 90 deg about Z, so "up" becomes -X; the lower joint's
    # Xrotation 90 does not move the lower joint itself.
    assert np.allclose(pos[1], [[1, 2, 3], [-9, 2, 3], [-9, 2, 8]], atol=1e-9)


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_rotation_channels_compose_in_listed_order(order):
    angles = {"X": 30.0, "Y": -50.0, "Z": 70.0}
    chans = " ".join(f"{a}rotation" for a in order)
    values = " ".join(str(angles[a]) for a in order)
    data = parse_bvh(ARM % (chans, values))
    mats = {"X": rx, "Y": ry, "Z": rz}
    r_upper = rz(90) @ mats[order[0]](angles[order[0]]) @ mats[order[1]](angles[order[1]]) \
        @ mats[order[2]](angles[order[2]])
    expected = np.array([1, 2, 3]) + rz(90) @ np.array([0, 10, 0]) + r_upper @ np.array([0, 0, 5])
    assert np.allclose(data.global_positions([2])[1, 0], expected, atol=1e-9)


def test_position_channels_replace_offset_and_may_follow_rotations():
    text = """HIERARCHY
ROOT r
{
  OFFSET 0 0 0
  CHANNELS 3 Yrotation Xposition Zposition
  JOINT j
  {
    OFFSET 7 7 7
    CHANNELS 4 Zrotation Yposition Xposition Zposition
    End Site
    {
      OFFSET 0 0 0
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.1
90 5 6 0 1 2 3
"""
    pos = parse_bvh(text).global_positions()[0]
    assert np.allclose(pos[0], [5, 0, 6])                       # root Y keeps its OFFSET value
    assert np.allclose(pos[1], [5, 0, 6] + ry(90) @ np.array([2, 1, 3]))


def _bvhio_positions(path):
    import bvhio
    root = bvhio.readAsHierarchy(str(path))
    joints = [j for j, _, _ in root.layout()]
    out = np.zeros((len(root.Keyframes), len(joints), 3))
    for f in range(out.shape[0]):
        root.loadPose(f, recursive=True)
        for k, j in enumerate(joints):
            p = j.PositionWorld
            out[f, k] = (p.x, p.y, p.z)
    return [j.Name for j in joints], out


def _random_skeleton_text(rng, frames=6):
    orders = ["XYZ", "ZXY", "YZX", "ZYX", "XZY", "YXZ"]
    lines = ["HIERARCHY", "ROOT root", "{", "OFFSET 0 0 0",
             "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    chans = [6]
    for k in range(5):
        o = orders[k]
        off = rng.normal(size=3) * 10
        lines += [f"JOINT j{k}", "{", "OFFSET " + " ".join(f"{v:.4f}" for v in off),
                  "CHANNELS 3 " + " ".join(f"{a}rotation" for a in o)]
        chans.append(3)
    lines += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * 6
    motion = rng.uniform(-170, 170, size=(frames, sum(chans)))
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.04"]
    lines += [" ".join(f"{v:.5f}" for v in row) for row in motion]
    return "\n".join(lines) + "\n"


def test_forward_kinematics_agrees_with_bvhio_on_random_rotations(tmp_path):
    pytest.importorskip("bvhio")
    text = _random_skeleton_text(np.random.default_rng(3))
    path = write(tmp_path, text)
    names, ref = _bvhio_positions(path)
    data = parse_bvh(path)
    ours = data.global_positions([data.names.index(n) for n in names])
    assert np.abs(ours - ref).max() < 1e-3


def test_parse_accepts_text_and_paths_alike(tmp_path):
    text = ARM % ("Zrotation Xrotation Yrotation", "0 0 0")
    path = write(tmp_path, text.replace("\n", "\r\n"))
    a, b = parse_bvh(text), parse_bvh(path)
    assert a.names == b.names and np.array_equal(a.motion, b.motion)
    assert b.source == str(path)


# ---------------------------------------------------------------- malformed input

GOOD = ARM % ("Zrotation Xrotation Yrotation", "0 0 0")

MALFORMED = {
    "not_bvh": ("just some words\n", "not a BVH"),
    "empty": ("", "not a BVH"),
    "no_motion": (GOOD.split("MOTION")[0], "no MOTION"),
    "truncated_rows": (GOOD.replace("Frames: 2", "Frames: 5"), "truncated"),
    "truncated_mid_row": (GOOD.rstrip("\n")[:-6] + "\n", "truncated"),
    "short_row": (GOOD.replace("1 2 3 0 0 0 0 0 0 0 0", "1 2 3 0 0 0 0 0 0 0"), "frame 0 has 10 values"),
    "nan": (GOOD.replace("1 2 3 90", "1 nan 3 90"), "nan"),
    "inf": (GOOD.replace("1 2 3 90", "1 inf 3 90"), "inf"),
    "word_in_data": (GOOD.replace("1 2 3 90", "1 two 3 90"), "'two'"),
    "zero_frames": (GOOD.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.1\n", "zero frames"),
    "bad_frame_time": (GOOD.replace("Frame Time: 0.5", "Frame Time: -1"), "Frame Time"),
    "missing_header": (GOOD.replace("Frames: 2\n", ""), "Frames:"),
    "bad_channel": (GOOD.replace("Zrotation Xrotation Yrotation\n", "Zrotation Wrotation Yrotation\n"),
                    "Wrotation"),
    "unbalanced": (GOOD.replace("  }\n}\nMOTION", "  }\nMOTION"), "ends inside joint"),
    "no_offset": (GOOD.replace("    OFFSET 0 10 0\n", ""), "no OFFSET"),
    "bad_offset": (GOOD.replace("OFFSET 0 10 0", "OFFSET 0 x 0"), "non-numeric"),
    "duplicate_joint": (GOOD.replace("JOINT lower", "JOINT upper"), "twice"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_raise_bvh_error_naming_file_and_reason(tmp_path, case):
    text, reason = MALFORMED[case]
    path = write(tmp_path, text, name=f"{case}.bvh")
    with pytest.raises(BvhError) as err:
        parse_bvh(path)
    msg = str(err.value)
    assert f"{case}.bvh" in msg and reason.lower() in msg.lower(), msg
    assert isinstance(err.value, ValueError)


def test_missing_file_directory_and_binary_raise_bvh_error(tmp_path):
    with pytest.raises(BvhError, match="nothere.bvh: file not found"):
        load_bvh(tmp_path / "nothere.bvh")
    with pytest.raises(BvhError, match="directory"):
        load_bvh(tmp_path)
    binary = tmp_path / "binary.bvh"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(BvhError, match="binary.bvh: not a BVH"):
        load_bvh(binary)


def test_unknown_joint_names_list_what_is_missing(tmp_path):
    path = write(tmp_path, GOOD, "arm.bvh")
    with pytest.raises(BvhError) as err:
        load_bvh(path)
    msg = str(err.value)
    assert "arm.bvh" in msg and "UpperLeg_L" in msg and "'mixamo'" in msg
    with pytest.raises(BvhError, match="unknown mapping"):
        load_bvh(path, mapping="nope")
    with pytest.raises(BvhError, match="missing"):
        load_bvh(path, mapping={"pelvis": "hips"})


# ---------------------------------------------------------------- mappings, units, resampling

@pytest.fixture(scope="module")
def walk():
    return synthetic_walk(60, turn=0.6)


@pytest.fixture(scope="module")
def represented_walk():
    """A walk as the model's outputs are: decoded from the 263-d representation."""
    j = rep.canonicalize(synthetic_walk(60, turn=0.6).astype(np.float64))
    return rep.features_to_joints(rep.joints_to_features(j)).astype(np.float32)


@pytest.fixture(scope="module")
def walk_text(walk):
    return bvh_text(walk)


def renamed(text, names):
    for ours, theirs in names.items():
        text = text.replace(f"JOINT {ours}\n", f"JOINT {theirs}\n").replace(f"ROOT {ours}\n", f"ROOT {theirs}\n")
    return text


def test_built_in_tables_cover_all_joints():
    assert set(MAPPINGS) == {"bandai", "salad", "smpl", "mixamo"}
    for table in MAPPINGS.values():
        assert tuple(table) == sk.JOINT_NAMES
    assert BANDAI_MAPPING["spine1"] == ("Hips", "Spine", 0.6)
    assert BANDAI_MAPPING["left_wrist"] == "Hand_L" and BANDAI_MAPPING["right_foot"] == "Toes_R"


@pytest.mark.parametrize("table,prefix,expected", [
    ("smpl", "", "smpl"),
    ("mixamo", "", "mixamo"),
    ("mixamo", "strip", "mixamo"),     # mixamo names without the namespace
    ("salad", "title", "salad"),       # "Left_hip" spelling of SMPL exporters
])
def test_auto_mapping_recognises_naming_schemes(tmp_path, walk, walk_text, table, prefix, expected):
    names = dict(MAPPINGS[table])
    if prefix == "strip":
        names = {k: v.split(":")[-1] for k, v in names.items()}
    elif prefix == "title":
        names = {k: v.capitalize() for k, v in names.items()}
    path = write(tmp_path, renamed(walk_text, names))
    clip = load_bvh(path)
    assert clip.mapping_name == expected
    assert np.abs(clip.joints - walk).max() < 1e-4


def test_bandai_names_use_blended_spine(tmp_path, walk, walk_text):
    # Name the synthetic skeleton's joints as Bandai does; its spine2 plays "Spine".
    names = {v: k for k, v in {
        "Hips": "pelvis", "Spine": "spine2", "Chest": "spine3", "Neck": "neck", "Head": "head",
        **{f"{b}_{s[0].upper()}": f"{s}_{j}" for s in ("left", "right") for b, j in (
            ("UpperLeg", "hip"), ("LowerLeg", "knee"), ("Foot", "ankle"), ("Toes", "foot"),
            ("Shoulder", "collar"), ("UpperArm", "shoulder"), ("LowerArm", "elbow"), ("Hand", "wrist"))},
    }.items()}
    clip = load_bvh(write(tmp_path, renamed(walk_text, names)))
    assert clip.mapping_name == "bandai"
    expect_spine1 = walk[:, 0] + 0.6 * (walk[:, 6] - walk[:, 0])
    assert np.abs(clip.joints[:, 3] - expect_spine1).max() < 1e-4
    assert np.abs(clip.joints[:, 20] - walk[:, 20]).max() < 1e-4


def test_custom_mapping_with_blend(tmp_path, walk, walk_text):
    table = dict(MAPPINGS["salad"])
    table["head"] = ("neck", "head", 2.0)     # extrapolate past the head joint
    clip = load_bvh(write(tmp_path, walk_text), mapping=table)
    assert clip.mapping_name == "custom"
    assert np.abs(clip.joints[:, 15] - (2 * walk[:, 15] - walk[:, 12])).max() < 1e-4
    table["head"] = ("neck", "head")
    with pytest.raises(BvhError, match="head"):
        load_bvh(write(tmp_path, walk_text), mapping=table)


@pytest.mark.parametrize("factor,scale", [(1.0, 1.0), (100.0, 0.01), (1000.0, 0.001)])
def test_units_are_detected(tmp_path, walk, factor, scale):
    path = tmp_path / "units.bvh"
    save_bvh(path, walk * factor, units="m")
    clip = load_bvh(path)
    assert clip.scale == scale
    assert np.abs(clip.joints - walk).max() < 1e-4
    assert detect_scale(walk * factor) == scale


def test_explicit_scale_overrides_detection(tmp_path, walk):
    path = tmp_path / "cm.bvh"
    save_bvh(path, walk)
    clip = load_bvh(path, scale=1.0)
    assert clip.scale == 1.0 and np.abs(clip.joints - walk * 100).max() < 1e-2
    with pytest.raises(BvhError, match="scale"):
        load_bvh(path, scale=-1)


def _linear_walk(frames, fps, speed=1.0):
    """The synthetic pose translated at `speed` m/s along +X, sampled at `fps`."""
    base = synthetic_walk(1)[0] - synthetic_walk(1)[0, 0] * np.array([1, 0, 1])
    t = np.arange(frames) / fps
    return (base[None] + (speed * t)[:, None, None] * np.array([1.0, 0, 0])).astype(np.float32), t


@pytest.mark.parametrize("source_fps", [30.0, 59.94, 24.0, 20.0, 120.0])
def test_resampling_to_20_fps_keeps_real_time(tmp_path, source_fps):
    frames = int(source_fps * 3) + 1
    joints, t = _linear_walk(frames, source_fps)
    path = tmp_path / "rate.bvh"
    save_bvh(path, joints, fps=source_fps)
    clip = load_bvh(path)
    assert clip.fps == 20.0 and abs(clip.source_fps - source_fps) < 1e-6
    duration = (frames - 1) / source_fps
    assert clip.joints.shape[0] == int(math.floor(duration * 20 + 1e-6)) + 1
    # Root x equals the time stamp of each output frame.
    expected_x = np.arange(clip.joints.shape[0]) / 20.0
    assert np.abs(clip.joints[:, 0, 0] - expected_x).max() < 1e-4
    native = load_bvh(path, fps=None)
    assert native.fps == pytest.approx(source_fps) and native.joints.shape[0] == frames


def test_resample_interpolates_linearly_and_handles_one_frame():
    x = np.arange(4, dtype=np.float64)[:, None] * 3.0      # 0, 3, 6, 9 at 30 fps
    out = resample(x, 30.0, 20.0)                            # t = 0, .05, .1
    assert np.allclose(out[:, 0], [0.0, 4.5, 9.0])
    assert resample(x[:1], 30.0, 20.0).shape == (1, 1)


def test_canonical_option_starts_at_origin_facing_forward(tmp_path, walk):
    turned = walk.copy()
    turned[..., [0, 2]] = -turned[..., [0, 2]]             # face -Z
    turned[..., 0] += 3.0
    path = tmp_path / "turned.bvh"
    save_bvh(path, turned)
    clip = load_bvh(path, canonical=True)
    assert np.abs(clip.joints[0, 0, [0, 2]]).max() < 1e-5
    assert abs(clip.joints[..., 1].min()) < 1e-5
    assert clip.joints[-1, 0, 2] > clip.joints[0, 0, 2] + 0.5   # walks forward along +Z
    assert clip.joints[0, 16, 0] > clip.joints[0, 17, 0]         # left shoulder at +X


# ---------------------------------------------------------------- export

def test_round_trip_reproduces_positions(tmp_path, walk):
    path = tmp_path / "walk.bvh"
    save_bvh(path, walk)
    clip = load_bvh(path)
    assert isinstance(clip, BvhClip)
    assert clip.joints.dtype == np.float32 and clip.joints.shape == walk.shape
    assert clip.mapping_name == "salad" and clip.source_path == str(path)
    assert np.linalg.norm(clip.joints - walk, axis=-1).max() < 0.01
    assert np.linalg.norm(clip.joints - walk, axis=-1).max() < 1e-4   # in fact exact up to print precision


def test_round_trip_of_a_single_frame_and_a_torch_tensor(tmp_path, walk):
    path = tmp_path / "one.bvh"
    save_bvh(path, torch.from_numpy(walk[5:6]))
    clip = load_bvh(path)
    assert clip.joints.shape == (1, 22, 3)
    assert np.abs(clip.joints - walk[5:6]).max() < 1e-4


def test_round_trip_of_a_non_rigid_motion_stays_close(tmp_path, walk):
    noisy = walk + np.random.default_rng(0).normal(scale=0.002, size=walk.shape).astype(np.float32)
    path = tmp_path / "noisy.bvh"
    save_bvh(path, noisy)
    err = np.linalg.norm(load_bvh(path).joints - noisy, axis=-1)
    assert err.max() < 0.02 and err.mean() < 0.01


def _round_trip_error(tmp_path, joints, units="cm"):
    """Distances (T, 22) in metres between joints and their export re-read by our reader."""
    path = tmp_path / f"round_trip_{units}.bvh"
    save_bvh(path, joints, units=units)
    return np.linalg.norm(load_bvh(path).joints - joints, axis=-1)


@pytest.mark.parametrize("units", ["cm", "m"])
def test_round_trip_of_the_representations_joints_is_within_a_millimetre(tmp_path, represented_walk, units):
    assert _round_trip_error(tmp_path, represented_walk, units).max() < 1e-3


@pytest.mark.shared_data
def test_round_trip_of_real_humanml3d_joints_is_within_a_millimetre(tmp_path, hml_sample):
    joints = rep.features_to_joints(hml_sample["features"])
    assert _round_trip_error(tmp_path, joints).max() < 1e-3


def test_centimetre_and_metre_files_read_back_alike(tmp_path, represented_walk):
    cm, m = tmp_path / "cm.bvh", tmp_path / "m.bvh"
    save_bvh(cm, represented_walk)                       # centimetres unless told otherwise
    save_bvh(m, represented_walk, units="m")
    a, b = load_bvh(cm), load_bvh(m)
    assert (a.scale, b.scale) == (0.01, 1.0)
    assert np.abs(a.joints - b.joints).max() < 1e-5
    assert np.allclose(parse_bvh(cm).offsets, 100 * parse_bvh(m).offsets, atol=1e-5)
    assert np.allclose(parse_bvh(cm).motion[:, :3], 100 * parse_bvh(m).motion[:, :3], atol=1e-4)  # root path
    Motion(represented_walk, np.zeros((len(represented_walk), 263))).save(m, bvh_units="cm")
    assert load_bvh(m).scale == 0.01


@pytest.mark.parametrize("units", ["mm", "CM", "metres", None, 100])
def test_units_other_than_cm_or_m_are_refused(tmp_path, walk, units):
    path = tmp_path / "x.bvh"
    with pytest.raises(ValueError, match=r"BVH units must be one of 'cm', 'm', got "):
        save_bvh(path, walk, units=units)
    with pytest.raises(ValueError, match="BVH units must be one of"):
        bvh_text(walk, units=units)
    with pytest.raises(ValueError, match="BVH units must be one of"):
        Motion(walk, np.zeros((len(walk), 263))).save(path, bvh_units=units)
    assert not path.exists()


COMMANDS_WRITING_BVH = (
    ["generate", "a person walks", "-o", "a.bvh"],
    ["edit", "a person walks", "-o", "out"],
    ["control", "a person walks", "--path", "0,0;0,2", "-o", "a.bvh"],
    ["edit-real", "in.bvh", "--source", "a person walks", "-o", "a.bvh"],
)


@pytest.mark.parametrize("argv", COMMANDS_WRITING_BVH, ids=lambda argv: argv[0])
def test_every_command_writing_bvh_takes_bvh_units(argv, capsys):
    parser = build_parser()
    assert parser.parse_args(argv).bvh_units == "cm"
    for units in UNITS_PER_METRE:
        assert parser.parse_args(argv + ["--bvh-units", units]).bvh_units == units
    with pytest.raises(SystemExit):
        parser.parse_args(argv + ["--bvh-units", "mm"])
    assert "invalid choice: 'mm'" in capsys.readouterr().err


def test_bones_of_a_non_rigid_motion_aim_at_its_joints(tmp_path, walk):
    """Where bone lengths drift, a re-read joint lies on the line from its re-read parent to the
    motion's joint, at the bone's rest length: it misses by the drift alone, and no error is
    passed down the chain."""
    noisy = walk + np.random.default_rng(1).normal(scale=0.005, size=walk.shape)
    path = tmp_path / "noisy.bvh"
    save_bvh(path, noisy)
    back = load_bvh(path).joints.astype(np.float64)
    rest = np.linalg.norm(parse_bvh(path).offsets, axis=-1) / 100.0
    names = parse_bvh(path).names
    for c in range(1, sk.NUM_JOINTS):
        p = sk.PARENTS[c]
        if p in (0, 9):          # one rotation serves all their children: least squares, not exact
            continue
        to_target = noisy[:, c] - back[:, p]
        bone = back[:, c] - back[:, p]
        length = rest[names.index(sk.JOINT_NAMES[c])]
        assert np.abs(np.linalg.norm(bone, axis=-1) - length).max() < 1e-5
        sine = np.linalg.norm(np.cross(bone, to_target), axis=-1) / (length * np.linalg.norm(to_target, axis=-1))
        assert sine.max() < 1e-5 and (np.sum(bone * to_target, axis=-1) > 0).all()     # same direction
        miss = np.abs(np.linalg.norm(to_target, axis=-1) - length)
        assert np.abs(np.linalg.norm(back[:, c] - noisy[:, c], axis=-1) - miss).max() < 1e-5


def test_exported_file_structure(tmp_path, walk):
    path = tmp_path / "structure.bvh"
    save_bvh(path, walk, fps=20.0)
    data = parse_bvh(path)
    assert set(data.names) == set(sk.JOINT_NAMES)
    assert data.channels[0][:3] == ("Xposition", "Yposition", "Zposition") and len(data.channels[0]) == 6
    assert all(len(c) == 3 and all(ch.endswith("rotation") for ch in c) for c in data.channels[1:])
    leaves = {data.names[j] for j in data.end_sites}
    assert leaves == {"head", "left_wrist", "right_wrist", "left_foot", "right_foot"}
    assert data.frame_time == pytest.approx(0.05) and data.num_frames == walk.shape[0]
    # Rest pose: upright T-pose facing +Z with the left side at +X.
    idx = {n: i for i, n in enumerate(data.names)}
    off = data.offsets
    assert off[idx["left_hip"], 0] > 0 > off[idx["right_hip"], 0]
    assert off[idx["spine1"], 1] > 0 and off[idx["left_knee"], 1] < 0
    assert off[idx["left_elbow"], 0] > 0 > off[idx["right_elbow"], 0]
    assert off[idx["left_foot"], 2] > 0
    lengths = np.linalg.norm(off[idx["left_knee"]])
    assert lengths == pytest.approx(38.0, abs=0.1)                # the motion's own thigh length, in cm


def _joints_in_bvhio(path, units):
    """(T, 22, 3) metres of one of our exports, as bvhio reads it."""
    names, ref = _bvhio_positions(path)
    return ref[:, [names.index(n) for n in sk.JOINT_NAMES]] / UNITS_PER_METRE[units]


@pytest.mark.parametrize("units", ["cm", "m"])
def test_exported_file_reads_the_same_in_bvhio(tmp_path, walk, represented_walk, units):
    pytest.importorskip("bvhio")
    for name, joints in (("walk", walk[:12]), ("represented", represented_walk[:12])):
        path = tmp_path / f"{name}.bvh"
        save_bvh(path, joints, units=units)
        err = np.linalg.norm(_joints_in_bvhio(path, units) - joints, axis=-1)
        assert err.max() < 1e-4, name                         # 1 mm asked; in fact print precision


# Runs inside Blender: imports the BVH with Blender's own importer and writes the world position of
# every bone's head (its joint) at the asked frames, turned back from Blender's Z-up world into the
# file's Y-up axes, in metres. The importer keys file frame i at scene frame frame_start + i.
# Debian's Blender 3.4 runs on Python 3.11, where its BVH importer's open(path, "rU") is an invalid mode; the
# importer's own module gets an open() that drops the "U" (universal newlines are Python 3's default anyway).
BLENDER_SCRIPT = """
import builtins, json, sys
import bpy
from bpy_extras.io_utils import axis_conversion
import io_anim_bvh.import_bvh as importer
importer.open = lambda file, mode="r", *a, **k: builtins.open(file, mode.replace("U", ""), *a, **k)
bvh, scale, frames, out = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.import_anim.bvh(filepath=bvh, global_scale=float(scale), axis_forward="-Z", axis_up="Y",
                        rotate_mode="NATIVE", frame_start=1, use_fps_scale=False)
arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
to_file = axis_conversion(from_forward="-Z", from_up="Y").to_4x4().inverted()
heads = {}
for f in map(int, frames.split(",")):
    bpy.context.scene.frame_set(f + 1)
    heads[f] = {b.name: list(to_file @ arm.matrix_world @ b.head) for b in arm.pose.bones}
with open(out, "w") as fh:
    json.dump(heads, fh)
"""


@pytest.mark.parametrize("units", ["cm", "m"])
def test_exported_file_reads_the_same_in_blender(tmp_path, represented_walk, units):
    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Blender is not installed (no `blender` on PATH): its BVH importer is not checked")
    path, out = tmp_path / f"walk_{units}.bvh", tmp_path / "heads.json"
    save_bvh(path, represented_walk, units=units)
    frames = (0, len(represented_walk) // 2, len(represented_walk) - 1)
    run = subprocess.run([blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr",
                          BLENDER_SCRIPT, "--", str(path), str(1.0 / UNITS_PER_METRE[units]),
                          ",".join(map(str, frames)), str(out)],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and out.is_file(), run.stdout[-2000:] + run.stderr[-2000:]
    heads = json.loads(out.read_text())
    ours = load_bvh(path, fps=None).joints
    for f in frames:
        got = np.array([heads[str(f)][name] for name in sk.JOINT_NAMES])
        assert np.linalg.norm(got - represented_walk[f], axis=-1).max() < 1e-3, f
        assert np.linalg.norm(got - ours[f], axis=-1).max() < 1e-3, f


def test_exported_rotations_change_smoothly(walk):
    fast_turn = synthetic_walk(80, turn=2.5)
    for motion in (walk, fast_turn):
        t = torch.from_numpy(motion.astype(np.float64))
        rots = local_rotations(t, rest_offsets(t))
        rel = rots[1:].transpose(-1, -2) @ rots[:-1]
        cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
        assert torch.rad2deg(torch.arccos(cos)).max() < 30.0
    data = parse_bvh(bvh_text(fast_turn))
    assert np.abs(np.diff(data.motion[:, 3:], axis=0)).max() < 30.0   # no Euler wraps


def test_save_is_atomic_and_validates(tmp_path, walk):
    path = tmp_path / "out.bvh"
    path.write_text("old")
    save_bvh(path, walk)
    assert path.read_text().startswith("HIERARCHY")
    assert sorted(os.listdir(tmp_path)) == ["out.bvh"]
    bad = walk.copy()
    bad[3, 4, 1] = np.nan
    for joints, fps, reason in [(bad, 20.0, "finite"), (walk[..., :2], 20.0, "shape"),
                                (walk[:0], 20.0, "zero frames"), (walk, 0.0, "fps")]:
        with pytest.raises(BvhError, match=reason):
            save_bvh(path, joints, fps=fps)
    with pytest.raises(BvhError, match="does not exist"):
        save_bvh(tmp_path / "missing" / "x.bvh", walk)
    assert path.read_text().startswith("HIERARCHY") and sorted(os.listdir(tmp_path)) == ["out.bvh"]


# ---------------------------------------------------------------- real Bandai-Namco clips

BANDAI_MEMBERS = ("dataset-1_walk_active_001.bvh", "dataset-2_wave-left-hand_active_011.bvh")


@pytest.fixture(scope="session")
def bandai_clips(shared_data, tmp_path_factory):
    """The two clips above, streamed out of the archive once per session (stops when both are found)."""
    archive = shared_data / "bandai-motiondataset-dev.tar.xz"
    if not archive.is_file():
        pytest.skip(f"{archive} is not present")
    out = tmp_path_factory.mktemp("bandai")
    wanted = set(BANDAI_MEMBERS)
    with tarfile.open(archive, "r|xz") as tar:
        for member in tar:
            base = os.path.basename(member.name)
            if member.isfile() and base in wanted:
                (out / base).write_bytes(tar.extractfile(member).read())
                wanted.discard(base)
                if not wanted:
                    break
    assert not wanted, f"archive lacks {wanted}"
    return {name: out / name for name in BANDAI_MEMBERS}


@pytest.mark.shared_data
def test_bandai_walk_imports_as_a_plausible_person(bandai_clips):
    path = bandai_clips["dataset-1_walk_active_001.bvh"]
    clip = load_bvh(path)
    assert clip.mapping_name == "bandai" and clip.scale == 0.01
    assert clip.source_fps == 30.0 and clip.fps == 20.0
    j = clip.joints
    head = np.median(j[:, 15, 1])
    assert 1.3 < head < 1.6                               # head joint; the skull top is ~0.2 m higher
    feet = j[:, [7, 8, 10, 11], 1]
    assert -0.03 < feet.min() < 0.06 and np.median(feet.min(axis=1)) < 0.1
    travel = j[-1, 0] - j[0, 0]
    assert abs(travel[2]) > 2.0 and abs(travel[2]) > 3 * abs(travel[0])
    facing_z = np.sign(travel[2])
    # Facing +Z the character's left is +X (and facing -Z, -X).
    assert np.mean((j[:, 20, 0] - j[:, 0, 0]) * facing_z) > 0.1
    assert np.mean((j[:, 21, 0] - j[:, 0, 0]) * facing_z) < -0.1
    canon = load_bvh(path, canonical=True).joints
    assert canon[-1, 0, 2] - canon[0, 0, 2] > 2.0


@pytest.mark.shared_data
def test_bandai_parse_agrees_with_bvhio(bandai_clips):
    pytest.importorskip("bvhio")
    path = bandai_clips["dataset-1_walk_active_001.bvh"]
    names, ref = _bvhio_positions(path)
    data = parse_bvh(path)
    ours = data.global_positions([data.names.index(n) for n in names])
    assert np.abs(ours - ref).max() < 1e-3               # centimetres


@pytest.mark.shared_data
def test_bandai_round_trip_within_a_centimetre(bandai_clips, tmp_path):
    clip = load_bvh(bandai_clips["dataset-1_walk_active_001.bvh"])
    path = tmp_path / "bandai_out.bvh"
    save_bvh(path, clip.joints)
    back = load_bvh(path)
    assert back.mapping_name == "salad"
    assert np.linalg.norm(back.joints - clip.joints, axis=-1).max() < 0.01


@pytest.mark.shared_data
def test_short_bandai_clip_loads(bandai_clips):
    path = bandai_clips["dataset-2_wave-left-hand_active_011.bvh"]
    try:
        clip = load_bvh(path)
    except BvhError as e:                                # allowed, if it names the file
        assert path.name in str(e)
        return
    assert clip.joints.shape == (13, 22, 3)              # 19 frames at 30 fps = 0.6 s
    assert np.isfinite(clip.joints).all()
