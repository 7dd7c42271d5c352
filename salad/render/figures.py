"""Interactive Plotly figures (3D skeleton with a frame slider, attention heatmaps) and a
static PNG of the heatmaps for export. Inputs are plain NumPy arrays."""
from __future__ import annotations

import functools
import os
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from salad.motion import skeleton as sk

import salad.render.style as style
from .geometry import BONES, HEAD

if TYPE_CHECKING:
    import plotly.graph_objects as go

PART_LABELS = tuple(n.replace("_", " ") for n in sk.BODY_PARTS.names)
MAX_FIGURE_FRAMES = 300     # keeps the figure's JSON small enough for a browser
BODY_BOX = 2.2              # metres: the side of the box the "body" view keeps around the character
VIEWS = ("body", "path")
FONT = "DejaVu Sans, Arial, sans-serif"


def _hex(rgb: np.ndarray) -> str:
    r, g, b = (int(round(float(c) * 255)) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def _plotly_colorscale() -> list[list]:
    stops = np.linspace(0.0, 1.0, len(style.ATTENTION_CMAP))
    return [[float(s), c] for s, c in zip(stops, style.ATTENTION_CMAP)]


# ------------------------------------------------------------------ inputs

def _check_attention(att, words, name: str = "attention") -> tuple[np.ndarray, list[str]]:
    arr = np.asarray(att, dtype=np.float64)
    if isinstance(words, str):
        words = [words]
    words = [str(w) for w in words]
    if arr.ndim == 2:
        arr = arr[None]
    n_parts = sk.BODY_PARTS.size
    if arr.ndim != 3 or arr.shape[1] != n_parts:
        raise ValueError(f"{name}: expected shape (n_words, {n_parts}, T) or ({n_parts}, T), "
                         f"got {np.shape(att)}")
    if arr.shape[2] == 0 or arr.shape[0] == 0:
        raise ValueError(f"{name}: empty (shape {arr.shape})")
    if len(words) != arr.shape[0]:
        raise ValueError(f"{name}: {arr.shape[0]} word rows but {len(words)} words")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN/inf")
    return arr, words


def _check_fps(fps) -> float:
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps: must be positive, got {fps}")
    return fps


def _color_range(arr: np.ndarray, zmax: float | None) -> tuple[float, float]:
    top = float(arr.max()) if zmax is None else float(zmax)
    return 0.0, top if top > 0 else 1.0


# ------------------------------------------------------------------ 3D skeleton

def _to_plot(p: np.ndarray) -> np.ndarray:
    """Data axes (x left, y up, z forward) -> Plotly axes (forward, left, up).
    A cyclic permutation, so the figure is not mirrored and Plotly's z is up."""
    return p[..., [2, 0, 1]]


def _bone_polyline() -> tuple[np.ndarray, np.ndarray]:
    """Joint indices of all bones as one polyline with breaks (-1), and each vertex's part."""
    idx, part = [], []
    for p, c in BONES:
        idx += [p, c, -1]
        part += [sk.PART_OF_JOINT[c]] * 2 + [0]
    return np.array(idx), np.array(part)


def _discrete_colorscale() -> list[list]:
    n = sk.BODY_PARTS.size
    scale = []
    for i, rgb in enumerate(style.PART_COLORS):
        scale += [[i / n, _hex(rgb)], [(i + 1) / n, _hex(rgb)]]
    return scale


def _body_boxes(pj: np.ndarray, shown: np.ndarray) -> tuple[np.ndarray, float]:
    """Per shown frame, the (x, y) ranges of a BODY_BOX square centred on the root, and the box's half side."""
    half = BODY_BOX / 2
    centres = pj[shown, 0, :2]
    return np.stack([centres - half, centres + half], axis=-1), half


def _polylines(pts: np.ndarray, idx: np.ndarray) -> list[dict]:
    """Per frame of pts (F, 22, 3), the bone polyline's x, y and z as lists, None at the breaks."""
    breaks = np.flatnonzero(idx < 0).tolist()
    coords = pts[:, np.where(idx < 0, 0, idx)].transpose(0, 2, 1).tolist()
    for frame in coords:
        for axis in frame:
            for b in breaks:
                axis[b] = None
    return [dict(zip("xyz", frame)) for frame in coords]


def _default_template() -> dict | None:
    """The template go.Figure would fill in: a spec sent to the browser as it is never passes
    through plotly.py, and without it the page would lose the default look."""
    import plotly.io as pio

    name = pio.templates.default
    return _template_json(name) if name else None


@functools.lru_cache(maxsize=4)
def _template_json(name: str) -> dict:
    # shared by every spec, read only: serialising the template once per figure is wasted work
    import plotly.io as pio

    return pio.templates[name].to_plotly_json()


def skeleton_figure_spec(joints: np.ndarray, fps: float = 20, title: str | None = None,
                         view: str = "body") -> dict:
    """skeleton_figure as a plain Plotly figure dict ({"data", "layout", "frames"}) of dicts,
    lists, strings and numbers, ready for json.dumps (breaks in the polylines are None, not NaN).
    Building plotly's objects for it, with their per-property validation, takes some thirty
    times as long, and a page that only needs the figure's JSON has no use for them."""
    from .video import _check_joints

    if view not in VIEWS:
        raise ValueError(f"view must be one of {', '.join(VIEWS)}, got {view!r}")
    j = _check_joints(joints)
    fps = _check_fps(fps)
    stride = int(np.ceil(len(j) / MAX_FIGURE_FRAMES))
    shown = np.arange(0, len(j), stride)
    pj = _to_plot(j)

    lo, hi = pj.reshape(-1, 3).min(0), pj.reshape(-1, 3).max(0)
    if view == "body":
        boxes, half = _body_boxes(pj, shown)
        x_rng, y_rng = boxes[0, 0].tolist(), boxes[0, 1].tolist()
        # the floor covers every box the view will visit
        floor_lo, floor_hi = boxes[:, :, 0].min(0), boxes[:, :, 1].max(0)
        z_rng = [0.0, max(float(hi[2]) + 0.2, BODY_BOX)]
    else:
        centre = (lo + hi) / 2
        half = max(float((hi - lo)[:2].max()) / 2 + 0.4, 1.0)
        x_rng = [float(centre[0]) - half, float(centre[0]) + half]
        y_rng = [float(centre[1]) - half, float(centre[1]) + half]
        floor_lo, floor_hi = np.array([x_rng[0], y_rng[0]]), np.array([x_rng[1], y_rng[1]])
        z_rng = [0.0, max(float(hi[2]) + 0.2, 2.0)]

    # Floor: a checker of 0.5 m tiles under the whole motion.
    tile = style.FLOOR_TILE
    ix = np.arange(np.floor(floor_lo[0] / tile), np.ceil(floor_hi[0] / tile))
    iy = np.arange(np.floor(floor_lo[1] / tile), np.ceil(floor_hi[1] / tile))
    gx, gy = np.meshgrid(ix, iy, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])
    quad = (np.stack([gx, gy], 1)[:, None, :] + corners) * tile
    verts = np.concatenate([quad.reshape(-1, 2), np.zeros((len(quad) * 4, 1))], axis=1)
    q = 4 * np.arange(len(quad))
    faces = np.concatenate([np.stack([q, q + 1, q + 2], 1), np.stack([q, q + 2, q + 3], 1)])
    tile_col = np.where((gx + gy) % 2 == 0, _hex(style.FLOOR_DARK), _hex(style.FLOOR_LIGHT)).tolist()
    floor = dict(type="mesh3d", x=verts[:, 0].tolist(), y=verts[:, 1].tolist(), z=verts[:, 2].tolist(),
                 i=faces[:, 0].tolist(), j=faces[:, 1].tolist(), k=faces[:, 2].tolist(),
                 facecolor=tile_col + tile_col, flatshading=True, hoverinfo="skip", showlegend=False,
                 name="floor", lighting=dict(ambient=1.0, diffuse=0.0))
    path = dict(type="scatter3d", x=pj[:, 0, 0].tolist(), y=pj[:, 0, 1].tolist(), z=[0.005] * len(pj),
                mode="lines", line=dict(color="#9aa3ad", width=3), name="root path", hoverinfo="skip")

    idx, part = _bone_polyline()

    def box(k: int) -> dict:
        if view != "body":
            return {}
        return dict(layout=dict(scene=dict(xaxis=dict(range=boxes[k, 0].tolist()),
                                           yaxis=dict(range=boxes[k, 1].tolist()))))

    # One trace for the whole body, coloured per vertex through a stepped colour scale:
    # frames then only carry coordinates, which keeps building and playing them fast.
    colors, sizes = (part + 0.5).tolist(), np.where(idx == HEAD, 13, 5).tolist()
    body = dict(
        type="scatter3d", **_polylines(pj[:1], idx)[0], mode="lines+markers", name="skeleton", showlegend=False,
        hoverinfo="skip",
        line=dict(color=colors, colorscale=_discrete_colorscale(), cmin=0, cmax=sk.BODY_PARTS.size, width=9),
        marker=dict(color=colors, colorscale=_discrete_colorscale(), cmin=0, cmax=sk.BODY_PARTS.size,
                    size=sizes, line=dict(width=0)))
    legend = [dict(type="scatter3d", x=[None], y=[None], z=[None], mode="markers", name=PART_LABELS[i],
                   marker=dict(color=_hex(style.PART_COLORS[i]), size=8), hoverinfo="skip")
              for i in range(sk.BODY_PARTS.size)]
    frames = [dict(data=[dict(type="scatter3d", **coords)], traces=[2], name=str(t), **box(k))
              for k, (t, coords) in enumerate(zip(shown.tolist(), _polylines(pj[shown], idx)))]
    frame_ms = 1000.0 * stride / fps
    steps = [dict(method="animate", label=f"{t / fps:.2f}",
                  args=[[str(t)], dict(mode="immediate", frame=dict(duration=0, redraw=True),
                                       transition=dict(duration=0))]) for t in shown.tolist()]

    def axis(text: str, rng: list) -> dict:
        return dict(title=dict(text=text, font=dict(size=11)), range=rng, backgroundcolor=_hex(style.BACKGROUND),
                    tickfont=dict(size=9))

    # closer in the body view: its box holds little more than the body
    eye = dict(x=1.2, y=0.85, z=0.5) if view == "body" else dict(x=1.35, y=0.95, z=0.55)
    layout = dict(
        title=dict(text=title or "", x=0.02, font=dict(family=FONT, size=16)),
        font=dict(family=FONT), paper_bgcolor="white", margin=dict(l=0, r=0, t=40 if title else 10, b=0),
        # Above the scene, wrapping into rows as the width requires; Plotly grows the top margin to fit.
        modebar=dict(orientation="v"),     # down the right side, off the legend
        legend=dict(orientation="h", y=1.0, x=0.0, xanchor="left", yanchor="bottom",
                    itemclick=False, itemdoubleclick=False, font=dict(size=11)),
        scene=dict(
            xaxis=axis("z (m), forward", x_rng),
            yaxis=axis("x (m), left", y_rng),
            zaxis=axis("y (m), up", z_rng),
            aspectmode="manual",
            aspectratio=dict(x=1.0, y=1.0, z=(z_rng[1] - z_rng[0]) / (2 * half)),
            camera=dict(eye=eye, up=dict(x=0, y=0, z=1)),
        ),
        updatemenus=[dict(
            type="buttons", direction="left", x=0.0, y=0.0, xanchor="left", yanchor="top",
            pad=dict(t=30, r=10), showactive=False,
            buttons=[dict(label="▶ play", method="animate",
                          args=[None, dict(frame=dict(duration=frame_ms, redraw=True), fromcurrent=True,
                                           transition=dict(duration=0), mode="immediate")]),
                     dict(label="❚❚ pause", method="animate",
                          args=[[None], dict(frame=dict(duration=0, redraw=False), mode="immediate",
                                             transition=dict(duration=0))])])],
        # Plotly labels only every n-th step where the labels would collide; only those steps get a
        # tick, as a tick per frame runs together into a bar.
        sliders=[dict(active=0, steps=steps, x=0.16, len=0.84, y=0.0, yanchor="top", pad=dict(t=20, l=14, r=14),
                      ticklen=6, minorticklen=0, font=dict(size=10),
                      currentvalue=dict(prefix="t = ", suffix=" s", font=dict(size=12)))],
    )
    template = _default_template()
    if template is not None:
        layout["template"] = template
    return dict(data=[floor, path, body] + legend, layout=layout, frames=frames)


def skeleton_figure(joints: np.ndarray, fps: float = 20, title: str | None = None,
                    view: str = "body") -> "go.Figure":
    """An orbitable 3D skeleton with a frame slider and play/pause; parts coloured, floor
    drawn, equal aspect. joints: (T, 22, 3) metres, Y up. view "body": a BODY_BOX metre box
    centred on the root that moves with it from frame to frame (each frame carries its scene
    ranges), so the body fills the view however far the motion travels; "path": one box
    around the whole motion. See skeleton_figure_spec for the same figure as a plain dict."""
    import plotly.graph_objects as go

    # plotly's per-property checks add a fifth to the time; the tests run them on the spec once
    return go.Figure(skeleton_figure_spec(joints, fps=fps, title=title, view=view), _validate=False)


# ------------------------------------------------------------------ attention

def _heatmap_trace(att_word: np.ndarray, fps: float, zrange, **kw) -> "go.Heatmap":
    import plotly.graph_objects as go

    t = np.arange(att_word.shape[1]) / fps
    return go.Heatmap(z=att_word, x=t, y=list(PART_LABELS), zmin=zrange[0], zmax=zrange[1],
                      colorscale=_plotly_colorscale(),
                      hovertemplate="%{y}<br>t = %{x:.2f} s<br>attention %{z:.3f}<extra></extra>", **kw)


def attention_heatmap(att_word: np.ndarray, word: str, fps: float = 20,
                      zmax: float | None = None) -> "go.Figure":
    """One word's attention over the 7 body parts (rows, root at the top) and time (seconds).
    att_word: (7, T)."""
    import plotly.graph_objects as go

    arr, words = _check_attention(att_word, [word], "att_word")
    fps = _check_fps(fps)
    fig = go.Figure(_heatmap_trace(arr[0], fps, _color_range(arr, zmax),
                                   colorbar=dict(title=dict(text="attention"), thickness=12)))
    fig.update_layout(
        title=dict(text=f"“{words[0]}” → body parts", x=0.02, font=dict(family=FONT, size=15)),
        font=dict(family=FONT), paper_bgcolor="white", plot_bgcolor="white",
        margin=dict(l=10, r=10, t=45, b=40), height=300,
        xaxis=dict(title="time (s)"), yaxis=dict(title="body part", autorange="reversed"))
    return fig


def attention_overview(att: np.ndarray, words: Sequence[str], fps: float = 20, cols: int = 3,
                       zmax: float | None = None) -> "go.Figure":
    """Small heatmaps for every word on one shared colour scale. att: (n_words, 7, T)."""
    from plotly.subplots import make_subplots

    arr, words = _check_attention(att, words)
    fps = _check_fps(fps)
    n = len(words)
    cols = max(1, min(int(cols), n))
    rows = int(np.ceil(n / cols))
    fig = make_subplots(rows=rows, cols=cols, subplot_titles=[f"“{w}”" for w in words],
                        shared_xaxes=True, shared_yaxes=True, horizontal_spacing=0.03,
                        vertical_spacing=min(0.12, 0.5 / rows))
    zr = _color_range(arr, zmax)
    for i in range(n):
        fig.add_trace(_heatmap_trace(arr[i], fps, zr, coloraxis="coloraxis", name=words[i]),
                      row=i // cols + 1, col=i % cols + 1)
    for r in range(1, rows + 1):
        fig.update_yaxes(autorange="reversed", row=r, col=1)
        fig.update_xaxes(title_text="time (s)" if r == rows else None, row=r)
    fig.update_yaxes(autorange="reversed")
    fig.update_layout(
        coloraxis=dict(colorscale=_plotly_colorscale(), cmin=zr[0], cmax=zr[1],
                       colorbar=dict(title=dict(text="attention"), thickness=12)),
        font=dict(family=FONT, size=11), paper_bgcolor="white", plot_bgcolor="white",
        margin=dict(l=10, r=10, t=40, b=40), height=max(260, 190 * rows))
    return fig


# matplotlib is not thread-safe (text rendering shares font objects across figures), and the studio draws
# PNGs from several request threads at once.
_MATPLOTLIB = threading.Lock()


def attention_png(att: np.ndarray, words: Sequence[str] | str, path: str | os.PathLike, fps: float = 20,
                  cols: int = 3, zmax: float | None = None, dpi: int = 150) -> Path:
    """The heatmaps as a PNG (one panel per word, shared colour scale), written atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LinearSegmentedColormap
    from matplotlib.figure import Figure

    from ..files import atomic_path
    from .video import _check_out

    out = _check_out(path, (".png",))
    arr, words = _check_attention(att, words)
    fps = _check_fps(fps)
    n, _, t_len = arr.shape
    cols = max(1, min(int(cols), n))
    rows = int(np.ceil(n / cols))
    # Fixed margins in inches instead of a layout engine: constrained layout measured every
    # tick label again and took more than half of the time.
    left, right, top, bottom, gap_w, gap_h, bar = 0.95, 0.95, 0.35, 0.5, 0.15, 0.4, 0.14
    width, height = left + right + 3.2 * cols + gap_w * (cols - 1), top + bottom + 1.6 * rows + gap_h * (rows - 1)
    with _MATPLOTLIB:
        fig = Figure(figsize=(width, height), dpi=dpi)
        FigureCanvasAgg(fig)
        fig.subplots_adjust(left=left / width, right=1 - right / width, top=1 - top / height, bottom=bottom / height,
                            wspace=gap_w / 3.2, hspace=gap_h / 1.6)
        axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False)).ravel()
        cmap = LinearSegmentedColormap.from_list("attention", [style.hex_rgb(c) for c in style.ATTENTION_CMAP])
        zr = _color_range(arr, zmax)
        extent = (0.0, t_len / fps, sk.BODY_PARTS.size - 0.5, -0.5)
        image = None
        for i, ax in enumerate(axes):
            if i >= n:
                ax.set_visible(False)
                continue
            image = ax.imshow(arr[i], aspect="auto", cmap=cmap, vmin=zr[0], vmax=zr[1], extent=extent,
                              interpolation="nearest")
            ax.set_title(f"“{words[i]}”", fontsize=10)
            ax.set_yticks(range(sk.BODY_PARTS.size), PART_LABELS, fontsize=8)
            ax.tick_params(axis="x", labelsize=8)
            if i // cols == rows - 1 or i + cols >= n:
                ax.set_xlabel("time (s)", fontsize=9)
                ax.tick_params(axis="x", labelbottom=True)
        cax = fig.add_axes([1 - (right - 0.25) / width, bottom / height, bar / width, 1 - (top + bottom) / height])
        fig.colorbar(image, cax=cax, label="attention")
        with atomic_path(out) as tmp:
            fig.savefig(tmp, format="png", facecolor="white")
    return out
