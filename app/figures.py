"""Adapting Plotly figures to Gradio's plot component.

Gradio draws a Plotly figure with `Plotly.react(data, layout, config)`, which drops
`figure.frames`; slider steps that `animate` to named frames then do nothing. Slider
steps that `restyle` the traces with each frame's coordinates (or `update` them, when the
frame also moves the scene's box) work without frames.
"""
from __future__ import annotations

import json

COORDS = ("x", "y", "z")


def frames_to_restyle_slider(spec: dict) -> dict:
    """A plain figure dict (as salad.render.skeleton_figure_spec makes) whose slider animates
    through frames (each frame holding new coordinates for some traces, and perhaps layout
    changes such as the scene's ranges) rewritten as one whose slider restyles (updates) those
    traces and that layout directly, without frames; play/pause buttons, which need frames, are
    left out and the slider takes their place. Returns a new dict; the input is left as it was
    (the two share their unchanged parts)."""
    layout = spec.get("layout") or {}
    if not spec.get("frames") or not layout.get("sliders"):
        return spec
    frames = {f.get("name"): f for f in spec["frames"]}
    out = {k: v for k, v in spec.items() if k != "frames"}
    layout = dict(layout)
    sliders = []
    for slider in layout["sliders"]:
        steps = []
        for step in slider.get("steps", ()):
            names = step.get("args", [None])[0]
            frame = frames.get(names[0]) if isinstance(names, (list, tuple)) and names else None
            if step.get("method") != "animate" or frame is None:
                steps.append(step)
                continue
            # as they are: lists (restyle does not decode plotly's base64 arrays)
            update = {k: [d.get(k) for d in frame["data"]] for k in COORDS}
            traces = list(frame["traces"]) if frame.get("traces") is not None else list(range(len(frame["data"])))
            relayout = _dotted(frame.get("layout") or {})
            if relayout:
                # dotted keys, so that only the ranges change and the user's camera stays
                steps.append(dict(step, method="update", args=[update, relayout, traces]))
            else:
                steps.append(dict(step, method="restyle", args=[update, traces]))
        sliders.append(dict(slider, steps=steps))
    if layout.pop("updatemenus", None):
        sliders = [dict(s, x=0.0, len=1.0) for s in sliders]
    out["layout"] = layout | {"sliders": sliders}
    return out


def plot_data(spec: dict):
    """A plain figure dict as gr.Plot takes it: Gradio passes a PlotData through as it is, where
    it would serialise a go.Figure (plotly's to_json), which costs more than building the dict.
    NaN is refused rather than sent: it is not JSON, and the browser would show no plot at all."""
    from gradio.components.plot import PlotData

    return PlotData(type="plotly", plot=json.dumps(spec, allow_nan=False, separators=(",", ":")))


def _dotted(spec: dict, prefix: str = "") -> dict:
    """{"scene": {"xaxis": {"range": r}}} -> {"scene.xaxis.range": r}."""
    out = {}
    for key, value in spec.items():
        if isinstance(value, dict) and value:
            out |= _dotted(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


PELVIS = 0
TARGET_COLOR = "#2fb673"     # the renderer's path green
ACHIEVED_COLOR = "#4f46e5"   # the studio's indigo
FONT = "DejaVu Sans, Arial, sans-serif"


def control_top_view(targets, mask, achieved=None):
    """The pelvis seen from above: its targets (constrained x and z) and, when given, the
    achieved path of `achieved` (T, 22, 3). The character starts facing up the plot (+z) with
    its left (+x) on the left, as a viewer standing behind it sees it."""
    import numpy as np
    import plotly.graph_objects as go

    tg, mk = np.asarray(targets, dtype=np.float64), np.asarray(mask, dtype=bool)
    on = mk[:, PELVIS, 0] & mk[:, PELVIS, 2]
    traces = []
    if on.any():
        idx = np.flatnonzero(on)
        # gaps in the constrained frames break the line, so separate keyframes stay dots
        broken = np.concatenate([[False], np.diff(idx) > 1])
        x, z = tg[idx, PELVIS, 0].tolist(), tg[idx, PELVIS, 2].tolist()
        for k in np.flatnonzero(broken)[::-1]:
            x.insert(int(k), None)
            z.insert(int(k), None)
        traces.append(go.Scatter(x=x, y=z, mode="lines+markers" if on.sum() < 12 else "lines",
                                 name="target", line=dict(color=TARGET_COLOR, width=5, dash="dot"),
                                 marker=dict(size=9, color=TARGET_COLOR),
                                 hovertemplate="target x %{x:.2f} m, z %{y:.2f} m<extra></extra>"))
    others = mk.any(-1)
    others[:, PELVIS] = False
    if others.any():
        t, j = np.nonzero(others)
        traces.append(go.Scatter(x=tg[t, j, 0], y=tg[t, j, 2], mode="markers", name="other joint targets",
                                 marker=dict(size=4, color=TARGET_COLOR, opacity=0.35), hoverinfo="skip"))
    if achieved is not None:
        a = np.asarray(achieved, dtype=np.float64)
        traces.append(go.Scatter(x=a[:, PELVIS, 0], y=a[:, PELVIS, 2], mode="lines", name="achieved",
                                 line=dict(color=ACHIEVED_COLOR, width=3),
                                 hovertemplate="achieved x %{x:.2f} m, z %{y:.2f} m<extra></extra>"))
    traces.append(go.Scatter(x=[0.0], y=[0.0], mode="markers", name="start", hoverinfo="skip",
                             marker=dict(symbol="triangle-up", size=13, color="#1f2328")))
    fig = go.Figure(traces)
    fig.update_layout(
        font=dict(family=FONT, size=11), height=320, margin=dict(l=10, r=10, t=30, b=10), paper_bgcolor="white",
        plot_bgcolor="#f4f5f7", legend=dict(orientation="h", y=1.0, yanchor="bottom", x=1.0, xanchor="right"),
        xaxis=dict(title="x (m), the character's left", autorange="reversed", zeroline=False),
        yaxis=dict(title="z (m), forward", scaleanchor="x", scaleratio=1, zeroline=False))
    return fig


def note_figure(text: str, height: int = 300):
    """An empty plot carrying a short note, for a view that has nothing to show."""
    import plotly.graph_objects as go

    fig = go.Figure()
    fig.add_annotation(text=text, x=0.5, y=0.5, xref="paper", yref="paper", showarrow=False,
                       font=dict(family=FONT, size=14, color="#59636e"))
    fig.update_layout(height=height, paper_bgcolor="white", plot_bgcolor="white", margin=dict(l=10, r=10, t=10, b=10),
                      xaxis=dict(visible=False), yaxis=dict(visible=False))
    return fig
