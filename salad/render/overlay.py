"""Text and legends burned into frames: drawn once with PIL, blended per frame in NumPy."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

import salad.render.style as style

_FONT_DIRS = (Path("/usr/share/fonts/truetype/dejavu"),)
_FONT_FILES = {"regular": "DejaVuSans.ttf", "bold": "DejaVuSans-Bold.ttf", "mono": "DejaVuSansMono.ttf"}


@lru_cache(maxsize=64)
def font(kind: str, px: int) -> ImageFont.ImageFont:
    """DejaVu at a pixel size: the system copy (fonts-dejavu-core) or matplotlib's bundled one."""
    name = _FONT_FILES[kind]
    dirs = list(_FONT_DIRS)
    try:
        import matplotlib

        dirs.append(Path(matplotlib.get_data_path()) / "fonts" / "ttf")
    except ImportError:  # matplotlib is a project dependency; this is only belt and braces
        pass
    for d in dirs:
        if (d / name).is_file():
            return ImageFont.truetype(str(d / name), px)
    return ImageFont.load_default(px)


# DejaVu has no CJK glyphs; text with any is drawn in a CJK font when one is installed
# (fonts-wqy-zenhei, fonts-noto-cjk), else in DejaVu, which shows boxes for the missing glyphs.
_CJK_FONTS = (Path("/usr/share/fonts/truetype/wqy/wqy-zenhei.ttc"),
              Path("/usr/share/fonts/opentype/noto/NotoSansCJK-Regular.ttc"),
              Path("/usr/share/fonts/opentype/noto/NotoSansCJK-Bold.ttc"))


def _has_cjk(text: str) -> bool:
    # CJK radicals, kana, ideographs, Hangul and full-width forms all lie at or above U+2E80
    return any(ord(c) >= 0x2E80 for c in text)


@lru_cache(maxsize=16)
def _cjk_font(px: int) -> ImageFont.ImageFont | None:
    for path in _CJK_FONTS:
        if path.is_file():
            return ImageFont.truetype(str(path), px)
    return None


def text_font(text: str, kind: str, px: int) -> ImageFont.ImageFont:
    """font(kind, px), or a CJK font at px when `text` needs one and one is installed."""
    return (_cjk_font(px) if _has_cjk(text) else None) or font(kind, px)


class Patch:
    """A premultiplied RGBA sprite placed at (x, y) that blends onto uint8 frames."""

    def __init__(self, rgba: np.ndarray, x: int, y: int):
        a = rgba[..., 3:4].astype(np.float32) / 255.0
        self.premul = rgba[..., :3].astype(np.float32) * a
        self.keep = 1.0 - a
        self.x, self.y = int(x), int(y)

    def blend(self, frame: np.ndarray) -> None:
        h, w = self.keep.shape[:2]
        x0, y0 = max(self.x, 0), max(self.y, 0)
        x1, y1 = min(self.x + w, frame.shape[1]), min(self.y + h, frame.shape[0])
        if x1 <= x0 or y1 <= y0:
            return
        sl = (slice(y0 - self.y, y1 - self.y), slice(x0 - self.x, x1 - self.x))
        region = frame[y0:y1, x0:x1]
        region[...] = (region * self.keep[sl] + self.premul[sl] + 0.5).astype(np.uint8)


def _wrap(text: str, fnt, max_width: int, max_lines: int) -> list[str]:
    words, lines, cur = text.split(), [], ""
    for word in words:
        trial = f"{cur} {word}".strip()
        if fnt.getlength(trial) <= max_width or not cur:
            cur = trial
        else:
            lines.append(cur)
            cur = word
    if cur:
        lines.append(cur)
    if len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] += " …"
    # A single word longer than the line is cut with an ellipsis.
    out = []
    for line in lines:
        while fnt.getlength(line) > max_width and len(line) > 2:
            line = line[:-2] + "…"
        out.append(line)
    return out


def label_patch(text: str, frame_w: int, frame_h: int, x: int | None = None, y: int | None = None,
                bold: bool = True, max_lines: int = 2, scale: float = 1.0) -> Patch:
    """Dark text on a rounded, translucent light plate; top-left by default."""
    px = max(11, int(round(frame_h * 0.037 * scale)))
    fnt = text_font(text, "bold" if bold else "regular", px)
    pad = max(4, px // 3)
    margin = max(6, frame_h // 40)
    lines = _wrap(text, fnt, frame_w - 2 * margin - 2 * pad, max_lines)
    asc, desc = fnt.getmetrics()
    line_h = asc + desc
    width = int(max(fnt.getlength(line) for line in lines)) + 2 * pad
    height = line_h * len(lines) + 2 * pad - desc // 2
    img = Image.new("RGBA", (width, height), (0, 0, 0, 0))
    d = ImageDraw.Draw(img)
    d.rounded_rectangle([0, 0, width - 1, height - 1], radius=pad + 1, fill=(255, 255, 255, 200))
    for i, line in enumerate(lines):
        d.text((pad, pad + i * line_h - desc // 4), line, font=fnt, fill=style.TEXT_COLOR + (255,))
    return Patch(np.asarray(img), margin if x is None else x, margin if y is None else y)


def legend_patch(frame_w: int, frame_h: int, cmap: str, label: str) -> Patch:
    """A small colour bar with its label and 0/1 ends, bottom-left, for tinted renders."""
    px = max(10, int(round(frame_h * 0.027)))
    fnt = text_font(label, "regular", px)
    margin = max(6, frame_h // 40)
    pad = max(3, px // 3)
    asc, desc = fnt.getmetrics()
    text_h = asc + desc
    bar_w, bar_h = max(60, frame_w // 4), max(6, text_h // 2)
    end_w = int(fnt.getlength("0")) + pad
    width = max(bar_w + 2 * end_w, int(fnt.getlength(label))) + 2 * pad
    bar_w = width - 2 * pad - 2 * end_w
    height = 2 * text_h + 2 * pad - desc // 2
    img = Image.new("RGBA", (width, height), (0, 0, 0, 0))
    d = ImageDraw.Draw(img)
    d.rounded_rectangle([0, 0, width - 1, height - 1], radius=pad + 1, fill=(255, 255, 255, 200))
    d.text((pad, pad - desc // 4), label, font=fnt, fill=style.TEXT_COLOR + (255,))
    row = pad + text_h - desc // 4
    grey = (90, 96, 104, 255)
    d.text((pad, row), "0", font=fnt, fill=grey)
    d.text((width - pad - fnt.getlength("1"), row), "1", font=fnt, fill=grey)
    ramp = (style.colormap(np.linspace(0, 1, bar_w), cmap) * 255).astype(np.uint8)
    rgba = np.asarray(img).copy()
    y0 = pad + text_h + (text_h - bar_h) // 2 - desc // 4
    x0 = pad + end_w
    rgba[y0:y0 + bar_h, x0:x0 + bar_w, :3] = ramp[None]
    rgba[y0:y0 + bar_h, x0:x0 + bar_w, 3] = 255
    return Patch(rgba, margin, frame_h - margin - height)


class Clock:
    """Bottom-right "1.25 s  26/120" readout. The monospaced glyphs are drawn once and
    pasted per frame, which is ~20x cheaper than laying out text with PIL every frame."""

    CHARS = "0123456789. s/"

    def __init__(self, frame_w: int, frame_h: int, fps: float, n_frames: int):
        px = max(10, int(round(frame_h * 0.027)))
        fnt = font("mono", px)
        self.fps, self.n = fps, n_frames
        margin = max(6, frame_h // 40)
        self.pad = max(3, px // 3)
        asc, desc = fnt.getmetrics()
        self.cell_w = int(round(fnt.getlength("0")))
        cell_h = asc + desc
        n_chars = len(self._text(n_frames - 1))
        self.w = self.cell_w * n_chars + 2 * self.pad
        self.h = cell_h + 2 * self.pad - desc // 2
        self.top = self.pad - desc // 4
        glyphs = Image.new("L", (self.cell_w * len(self.CHARS), cell_h), 0)
        d = ImageDraw.Draw(glyphs)
        for i, ch in enumerate(self.CHARS):
            d.text((i * self.cell_w, 0), ch, font=fnt, fill=255)
        self.glyphs = np.asarray(glyphs).reshape(cell_h, len(self.CHARS), self.cell_w).transpose(1, 0, 2)
        plate = Image.new("RGBA", (self.w, self.h), (0, 0, 0, 0))
        ImageDraw.Draw(plate).rounded_rectangle([0, 0, self.w - 1, self.h - 1], radius=self.pad + 1,
                                               fill=(255, 255, 255, 185))
        self.plate = np.asarray(plate).astype(np.float32)
        self.ink = np.array([70, 76, 84], np.float32)
        self.x, self.y = frame_w - margin - self.w, frame_h - margin - self.h

    def _text(self, t: int) -> str:
        digits = len(str(self.n))
        return f"{t / self.fps:5.2f} s  {t + 1:>{digits}d}/{self.n}"

    def patch(self, t: int) -> Patch:
        text = self._text(t)
        cover = np.zeros((self.glyphs.shape[1], self.cell_w * len(text)), np.float32)
        idx = [self.CHARS.index(c) for c in text]
        cover[:] = np.concatenate(list(self.glyphs[idx]), axis=1) / 255.0
        rgba = self.plate.copy()
        h = min(cover.shape[0], self.h - self.top)
        region = rgba[self.top:self.top + h, self.pad:self.pad + cover.shape[1]]
        a = cover[:h, :, None]
        region[..., :3] = region[..., :3] * (1 - a) + self.ink * a
        region[..., 3:] = np.maximum(region[..., 3:], 255 * a)
        return Patch(rgba, self.x, self.y)
