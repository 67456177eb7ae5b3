"""Compare rendered frames with reference images, tolerating software-GL noise.

Two renderings of the same scene by different OpenGL implementations (or
versions of Mesa's llvmpipe) differ by rounding in shading, by a pixel here
and there along edges, and in text anti-aliasing. A different scene (a
tool moved by a few millimetres, a structure missing, another camera)
changes a compact region of many pixels by a lot. :func:`compare_images`
therefore measures

* ``mad``: the mean absolute difference over all pixels and channels
  [0-255 counts];
* ``frac``: the fraction of pixels whose largest channel difference exceeds
  ``pixel_tol`` counts;

and calls the images equal when ``mad <= mad_tol`` and ``frac <= frac_tol``.
The defaults accept llvmpipe's differences and reject a tool moved by
1 mm in a 400 x 300 view of the phantom (see the tests).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MAD_TOL", "FRAC_TOL", "PIXEL_TOL", "ImageDiff", "compare_images",
           "read_png", "write_png", "diff_image"]

#: Default tolerances (see the module docstring).
MAD_TOL = 2.0
FRAC_TOL = 0.004
PIXEL_TOL = 48


@dataclass(frozen=True)
class ImageDiff:
    """Result of :func:`compare_images`.

    Attributes
    ----------
    same : bool
        Within tolerance.
    mad : float
        Mean absolute difference per channel [counts].
    frac : float
        Fraction of pixels differing by more than ``pixel_tol``.
    max_diff : int
        Largest channel difference [counts].
    reason : str
        Why they differ ("" if same).
    """

    same: bool
    mad: float
    frac: float
    max_diff: int
    reason: str = ""

    def __bool__(self):
        return self.same


def compare_images(a: np.ndarray, b: np.ndarray, mad_tol: float = MAD_TOL,
                   frac_tol: float = FRAC_TOL, pixel_tol: int = PIXEL_TOL) -> ImageDiff:
    """Compare two RGB(A) uint8 images of the same size (alpha is ignored).

    Parameters
    ----------
    a, b : (h, w, 3 or 4) uint8
    mad_tol : float
        Largest accepted mean absolute difference [counts].
    frac_tol : float
        Largest accepted fraction of differing pixels.
    pixel_tol : int
        A pixel differs when a channel differs by more than this [counts].
    """
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape[:2] != b.shape[:2]:
        return ImageDiff(False, float("inf"), 1.0, 255,
                         f"sizes differ: {a.shape[1]}x{a.shape[0]} vs {b.shape[1]}x{b.shape[0]}")
    d = np.abs(a[..., :3].astype(np.int16) - b[..., :3].astype(np.int16))
    mad = float(d.mean())
    per_px = d.max(axis=2)
    frac = float(np.count_nonzero(per_px > pixel_tol)) / per_px.size
    mx = int(per_px.max()) if per_px.size else 0
    reasons = []
    if mad > mad_tol:
        reasons.append(f"mean abs difference {mad:.3f} > {mad_tol}")
    if frac > frac_tol:
        reasons.append(f"{100 * frac:.3f}% of pixels differ by > {pixel_tol} "
                       f"(limit {100 * frac_tol:.3f}%)")
    return ImageDiff(not reasons, mad, frac, mx, "; ".join(reasons))


def read_png(path) -> np.ndarray:
    """(h, w, 3) uint8 RGB of a PNG file, first row at the top."""
    from PIL import Image

    with Image.open(Path(path)) as im:
        return np.asarray(im.convert("RGB")).copy()


def write_png(path, image: np.ndarray) -> Path:
    """Write an (h, w, 3) uint8 image (first row at the top) as PNG."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image[..., :3], dtype=np.uint8)).save(path,
                                                                             optimize=True)
    return path


def diff_image(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Visual diff for humans: the per-pixel max difference, amplified x4."""
    d = np.abs(a[..., :3].astype(np.int16) - b[..., :3].astype(np.int16)).max(axis=2)
    g = np.clip(d * 4, 0, 255).astype(np.uint8)
    return np.stack([g, g, g], axis=2)
