"""Look of the renders: body-part palette, sizes, lights and the shading model.

Shading is evaluated per vertex in NumPy and handed to the GPU as vertex colours
(pyrender's unlit "flat" pipeline): the software rasteriser only interpolates colours,
with no per-pixel lighting or light uniforms to bind, and the look is fully ours to tune.
"""
from __future__ import annotations

import numpy as np


def hex_rgb(code: str) -> np.ndarray:
    code = code.lstrip("#")
    return np.array([int(code[i:i + 2], 16) for i in (0, 2, 4)], dtype=np.float64) / 255.0


# Left side in blues, right side in warm reds/oranges, the trunk in neutrals; legs are the
# darker shade of each side so that crossing limbs stay tellable apart.
PART_COLORS = np.stack([hex_rgb(c) for c in (
    "#5f6b78",  # root
    "#2f6fba",  # left lower
    "#c8423c",  # right lower
    "#8d98a3",  # spine
    "#62b0ea",  # left upper
    "#f0924a",  # right upper
    "#e3c869",  # head
)])

BACKGROUND = hex_rgb("#e6e9ed")
FLOOR_LIGHT = hex_rgb("#f4f5f7")
FLOOR_DARK = hex_rgb("#d5d9de")
FLOOR_TILE = 0.5            # metres per checker square
MSAA_SAMPLES = 4            # multisampling of every frame (salad.render.engine)
FLOOR_RADIUS = 14.0         # the floor fades into the background over its outer part
FLOOR_FADE_START = 0.35     # fraction of the radius that keeps its colours
# The checker's contrast fades out between these distances (m): far squares are a few pixels
# wide, and without multisampling (previews) their edges would shimmer from frame to frame.
FLOOR_CONTRAST_START = 3.0
FLOOR_CONTRAST_END = 8.0
SHADOW_COLOR = hex_rgb("#23272e")
SHADOW_OPACITY = 0.5
SHADOW_FALLOFF = 0.35        # metres of height over which a shadow fades to 1/e
# Shadows fall from a light almost overhead (camera axes right/up/back): they stay under
# the feet, where they show contact, instead of stretching across the floor.
SHADOW_LIGHT = np.array([-0.25, 1.0, -0.15])
TARGET_COLOR = hex_rgb("#52c98e")      # every constrained frame: a light green unused by the parts
TARGET_ACTIVE_COLOR = hex_rgb("#0f9a55")  # this frame's targets
PATH_COLOR = hex_rgb("#2fb673")
TEXT_COLOR = (31, 35, 40)

# Sizes in metres for a 1.7 m adult; scaled with the skeleton's size.
JOINT_RADIUS = 0.04
HEAD_RADIUS = 0.095
BONE_RADIUS_TRUNK = 0.038
BONE_RADIUS_LIMB = 0.03
TARGET_RADIUS = 0.022
TARGET_ACTIVE_RADIUS = 0.038
CONNECTOR_RADIUS = 0.007
REFERENCE_HEIGHT = 1.7

# Pelvis-to-head chain, hips and collar bones are drawn thicker than the limbs.
TRUNK_BONES = {(0, 3), (3, 6), (6, 9), (9, 12), (12, 15), (0, 1), (0, 2), (9, 13), (9, 14)}

# Lights as (direction towards the light in camera axes right/up/back, intensity).
KEY = (np.array([-0.45, 1.0, 0.55]), 0.95)
FILL = (np.array([0.85, 0.25, 0.6]), 0.30)
RIM = (np.array([0.35, 0.55, -1.0]), 0.45)
SKY_AMBIENT = 0.42
GROUND_AMBIENT = 0.16
SPECULAR = 0.22
SHININESS = 36.0


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.power(np.clip(c, 0.0, 1.0), 2.2)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.power(np.clip(c, 0.0, 1.0), 1.0 / 2.2)


def light_dirs(right: np.ndarray, up: np.ndarray, back: np.ndarray) -> dict[str, tuple[np.ndarray, float]]:
    """World-space unit directions towards each light, from the camera axes (3,) each."""
    out = {}
    for name, (d, k) in {"key": KEY, "fill": FILL, "rim": RIM, "shadow": (SHADOW_LIGHT, 0.0)}.items():
        w = d[0] * right + d[1] * up + d[2] * back
        out[name] = (w / np.linalg.norm(w), k)
    return out


def shade(albedo: np.ndarray, normals: np.ndarray, view: np.ndarray,
          lights: dict[str, tuple[np.ndarray, float]]) -> np.ndarray:
    """sRGB colours of surfaces with sRGB albedo (..., 3), unit normals (..., 3), view
    direction towards the camera (3,); hemisphere ambient + key/fill Lambert + Blinn
    specular + a rim light that separates the figure from the floor."""
    n_up = normals[..., 1]
    ambient = GROUND_AMBIENT + (SKY_AMBIENT - GROUND_AMBIENT) * 0.5 * (n_up + 1.0)
    key_dir, key_k = lights["key"]
    fill_dir, fill_k = lights["fill"]
    rim_dir, rim_k = lights["rim"]
    n_key = normals @ key_dir
    diffuse = (ambient + key_k * np.clip(n_key, 0.0, None)
               + fill_k * np.clip(normals @ fill_dir, 0.0, None))
    half = key_dir + view
    half = half / np.linalg.norm(half)
    spec = SPECULAR * np.power(np.clip(normals @ half, 0.0, None), SHININESS) * (n_key > 0)
    facing = np.clip(normals @ view, 0.0, 1.0)
    rim = rim_k * np.power(1.0 - facing, 3.0) * np.clip(normals @ rim_dir + 0.3, 0.0, None)
    lin = srgb_to_linear(albedo) * (diffuse + rim)[..., None] + spec[..., None]
    # Soft shoulder instead of a hard clip keeps bright parts from flattening to white.
    lin = lin / (1.0 + 0.25 * lin)
    return linear_to_srgb(lin * 1.25)


# Low attention recedes into a cool grey, high attention glows amber to crimson: the
# joints a word drives stand out while the rest of the body stays readable.
ATTENTION_CMAP = ("#8f9aa6", "#c9b48f", "#f2a541", "#e4572e", "#c1121f")


def colormap(values: np.ndarray, name: str = "attention") -> np.ndarray:
    """sRGB colours (..., 3) of values in [0, 1] through "attention" or any matplotlib map."""
    from matplotlib import colormaps
    from matplotlib.colors import LinearSegmentedColormap

    if name == "attention":
        cmap = LinearSegmentedColormap.from_list("attention", [hex_rgb(c) for c in ATTENTION_CMAP])
    elif name in colormaps:
        cmap = colormaps[name]
    else:
        raise ValueError(f"cmap: unknown colormap {name!r}; use 'attention' or a matplotlib name")
    return cmap(np.clip(values, 0.0, 1.0))[..., :3]
