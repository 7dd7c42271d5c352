"""Adapting Plotly figures to Gradio's plot component.

Gradio draws a Plotly figure with `Plotly.react(data, layout, config)`, which drops
`figure.frames`; slider steps that `animate` to named frames then do nothing. Slider
steps that `restyle` the traces with each frame's coordinates work without frames.
"""
from __future__ import annotations

COORDS = ("x", "y", "z")


def frames_to_restyle_slider(fig):
    """Rewrite a figure whose slider animates through frames (each frame holding only new
    coordinates for some traces) into one whose slider restyles those traces directly.
    Play/pause buttons, which need frames, are removed. Returns the figure (changed in place)."""
    frames = {f.name: f for f in fig.frames or ()}
    if not frames or not fig.layout.sliders:
        return fig
    sliders = []
    for slider in fig.layout.sliders:
        steps = []
        for step in slider.steps:
            names = step.args[0] if step.args else None
            frame = frames.get(names[0]) if isinstance(names, (list, tuple)) and names else None
            if step.method != "animate" or frame is None:
                steps.append(step)
                continue
            update = {k: [getattr(d, k) for d in frame.data] for k in COORDS}
            traces = list(frame.traces) if frame.traces is not None else list(range(len(frame.data)))
            steps.append(dict(method="restyle", label=step.label, args=[update, traces]))
        sliders.append(slider.update(steps=steps))
    fig.layout.sliders = sliders
    fig.layout.updatemenus = ()      # update_layout(updatemenus=[]) would leave them in place
    fig.frames = ()
    return fig
