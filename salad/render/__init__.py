"""Rendering: offscreen skeleton videos (pyrender on EGL or OSMesa) and Plotly/PNG figures.

Importing this package does not import OpenGL; the GL platform is chosen at the
first render (see `gl_backend`).
"""
from .backend import gl_backend
from .figures import attention_heatmap, attention_overview, attention_png, skeleton_figure, skeleton_figure_spec
from .video import (
    last_render_stats, render_frames, render_side_by_side, render_video, save_frame_strip, save_gif, warm_up,
)
from .workers import start as start_workers, stop as stop_workers

__all__ = [
    "attention_heatmap", "attention_overview", "attention_png", "gl_backend", "last_render_stats",
    "render_frames", "render_side_by_side", "render_video", "save_frame_strip", "save_gif",
    "skeleton_figure", "skeleton_figure_spec", "start_workers", "stop_workers", "warm_up",
]
