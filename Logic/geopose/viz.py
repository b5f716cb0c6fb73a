"""Small picture helpers (numpy + Pillow): windowing, colour overlays, PNG output."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from PIL import Image, ImageDraw

__all__ = ["to_uint8", "to_rgb", "overlay_mask", "draw_points", "label_panel", "save_png", "hstack", "vstack"]

Colour = tuple[int, int, int]


def to_uint8(image: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.5)) -> np.ndarray:
    """Window a 2D float image to 8 bits between two percentiles."""
    img = np.asarray(image, dtype=np.float32)
    lo, hi = np.percentile(img, percentiles) if img.size else (0.0, 1.0)
    if hi <= lo:
        hi = lo + 1.0
    return (np.clip((img - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8)


def to_rgb(image: np.ndarray) -> np.ndarray:
    g = image if image.dtype == np.uint8 else to_uint8(image)
    return np.repeat(g[..., None], 3, axis=-1)


def overlay_mask(rgb: np.ndarray, mask: np.ndarray, colour: Colour, alpha: float = 0.45, outline: bool = False) -> np.ndarray:
    """Blend ``colour`` over ``rgb`` where ``mask``; ``outline`` keeps only the mask's border."""
    m = np.asarray(mask, bool)
    if outline:
        inner = m.copy()
        inner[1:-1, 1:-1] = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
        m = m & ~inner
    out = rgb.astype(np.float32).copy()
    out[m] = (1 - alpha) * out[m] + alpha * np.asarray(colour, np.float32)
    return out.astype(np.uint8)


def draw_points(rgb: np.ndarray, points_rc: np.ndarray, colour: Colour, radius: float = 1.0) -> np.ndarray:
    """Draw (row, col) points as small discs."""
    img = Image.fromarray(rgb)
    d = ImageDraw.Draw(img)
    for r, c in np.asarray(points_rc, float):
        d.ellipse((c - radius, r - radius, c + radius, r + radius), fill=colour)
    return np.asarray(img)


def label_panel(rgb: np.ndarray, text: str, colour: Colour = (255, 255, 255)) -> np.ndarray:
    """Write a caption in the top-left corner (on a dark band)."""
    img = Image.fromarray(rgb)
    d = ImageDraw.Draw(img)
    box = d.textbbox((3, 2), text)
    d.rectangle((0, 0, box[2] + 3, box[3] + 3), fill=(0, 0, 0))
    d.text((3, 2), text, fill=colour)
    return np.asarray(img)


def _pad_to(panels: Sequence[np.ndarray], axis: int) -> list[np.ndarray]:
    other = 0 if axis == 1 else 1
    size = max(p.shape[other] for p in panels)
    out = []
    for p in panels:
        pad = [(0, 0)] * p.ndim
        pad[other] = (0, size - p.shape[other])
        out.append(np.pad(p, pad))
    return out


def _stack(panels: Iterable[np.ndarray], axis: int, gap: int) -> np.ndarray:
    panels = _pad_to(list(panels), axis)
    spaced = []
    for i, p in enumerate(panels):
        spaced.append(p)
        if i < len(panels) - 1:
            shape = list(p.shape)
            shape[axis] = gap
            spaced.append(np.zeros(shape, p.dtype))
    return np.concatenate(spaced, axis=axis)


def hstack(panels: Iterable[np.ndarray], gap: int = 4) -> np.ndarray:
    """Panels side by side (padded to the tallest), ``gap`` black pixels apart."""
    return _stack(panels, 1, gap)


def vstack(panels: Iterable[np.ndarray], gap: int = 4) -> np.ndarray:
    """Panels one above the other (padded to the widest)."""
    return _stack(panels, 0, gap)


def save_png(rgb: np.ndarray, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path)
    return path
