"""A look at one dataset frame: the RGB picture, its depth as a colour map
and its segmentation over the picture, side by side, with a legend (numpy
and Pillow only).

``bonesim dataset RUN.h5 --out frames.h5 --preview FILE.png`` writes one for
the middle frame; :func:`preview` makes it from any frame's streams.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["turbo", "depth_colors", "overlay", "preview", "write_preview"]

# Turbo colour map as a polynomial in t (Mikhailov's published fit, 2019).
_TURBO = np.array([
    [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
    [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
    [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973]])


def turbo(t) -> np.ndarray:
    """RGB uint8 (..., 3) of values ``t`` in [0, 1] on the turbo colour map."""
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    powers = np.stack([t ** p for p in range(6)], axis=-1)
    return np.clip(np.rint(powers @ _TURBO.T * 255.0), 0, 255).astype(np.uint8)


def depth_colors(depth, lo=None, hi=None) -> np.ndarray:
    """A depth map [mm] as turbo colours (near red, far blue; NaN black),
    scaled between its 2nd and 98th percentiles unless ``lo``/``hi`` given."""
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d)
    out = np.zeros(d.shape + (3,), np.uint8)
    if not ok.any():
        return out
    lo = float(np.percentile(d[ok], 2)) if lo is None else float(lo)
    hi = float(np.percentile(d[ok], 98)) if hi is None else float(hi)
    out[ok] = turbo(1.0 - (d[ok] - lo) / max(hi - lo, 1e-9))
    return out


def overlay(rgb, cls, classes, alpha: float = 0.55, edges: bool = True) -> np.ndarray:
    """The class map's preview colours blended over the picture (background
    left as it is), with the borders between classes drawn dark."""
    lut = np.zeros((256, 3), np.float64)
    for c in classes:
        lut[int(c["id"])] = c.get("rgb", (200, 200, 200))
    col = lut[np.asarray(cls, np.intp)]
    base = np.asarray(rgb, np.float64)
    m = (np.asarray(cls) != 0)[..., None]
    out = np.where(m, (1 - alpha) * base + alpha * col, base)
    if edges:
        c = np.asarray(cls)
        e = np.zeros(c.shape, bool)
        e[:, 1:] |= c[:, 1:] != c[:, :-1]
        e[1:, :] |= c[1:, :] != c[:-1, :]
        out[e] = 0.25 * out[e]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def preview(streams: dict, classes, title: str = "") -> np.ndarray:
    """Side-by-side RGB | depth | segmentation (whichever the frame has), a
    legend of the classes shown and the depth range under them; (H', W', 3) uint8."""
    from PIL import Image, ImageDraw

    panels, notes = [], []
    rgb = streams.get("rgb")
    if rgb is not None:
        panels.append(np.asarray(rgb, np.uint8))
    if "depth" in streams:
        d = np.asarray(streams["depth"], np.float64)
        panels.append(depth_colors(d))
        ok = np.isfinite(d)
        if ok.any():
            notes.append(f"depth {np.percentile(d[ok], 2):.1f} mm (red) .. "
                         f"{np.percentile(d[ok], 98):.1f} mm (blue)")
    shown = []
    if "class" in streams:
        cls = np.asarray(streams["class"])
        base = rgb if rgb is not None else np.zeros(cls.shape + (3,), np.uint8)
        panels.append(overlay(base, cls, classes))
        present = set(np.unique(cls).tolist())
        shown = [c for c in classes if c["id"] in present and c["id"] != 0]
    h = max(p.shape[0] for p in panels)
    row = np.concatenate([np.pad(p, ((0, h - p.shape[0]), (0, 4), (0, 0))) for p in panels],
                         axis=1)
    legend_h = 16 * (1 + (len(shown) + 3) // 4) + 16 * len(notes) + 8
    img = Image.new("RGB", (row.shape[1], h + legend_h), (20, 22, 26))
    img.paste(Image.fromarray(row), (0, 0))
    dr = ImageDraw.Draw(img)
    y = h + 4
    if title:
        dr.text((6, y), title, fill=(235, 235, 230))
        y += 16
    col_w = max(row.shape[1] // 4, 1)
    for q, c in enumerate(shown):
        x = 6 + (q % 4) * col_w
        yy = y + 16 * (q // 4)
        rgb = tuple(int(v) for v in c.get("rgb", (200, 200, 200)))
        dr.rectangle([x, yy + 2, x + 10, yy + 12], fill=rgb)
        dr.text((x + 14, yy), f"{c['id']} {c['shown_as']}", fill=(235, 235, 230))
    y += 16 * ((len(shown) + 3) // 4)
    for line in notes:
        dr.text((6, y), line, fill=(200, 200, 200))
        y += 16
    return np.asarray(img)


def write_preview(path, streams: dict, classes, title: str = "") -> Path:
    """:func:`preview` saved as a PNG; returns the path."""
    from PIL import Image

    path = Path(path)
    Image.fromarray(preview(streams, classes, title)).save(path)
    return path
