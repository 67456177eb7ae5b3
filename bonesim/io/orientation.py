"""Axis-orientation codes: how an image stack's axes lie in the patient frame.

Every case lives in one patient frame, LPS (as DICOM and 3D Slicer use):
``+x`` toward the patient's left, ``+y`` posterior, ``+z`` superior.

A stack of images (a label stack, a raw volume without a header) carries no
orientation of its own, so its manifest declares one as a three-letter code
(nibabel's axis-code convention): the letters are for the stack's image
columns, image rows (top row first) and slices (in file order), in turn, and
each names the direction in which that axis *increases*: ``L`` or ``R``,
``P`` or ``A``, ``S`` or ``I``. ``"LPS"`` is the patient frame itself;
``"PLS"`` means columns run toward posterior, rows toward the left and
slices upward. Codes of either handedness are valid: a left-handed code
describes a stack stored mirrored, and reorienting it puts the anatomy back
on its true side.

Functions here only permute and flip axes (never interpolate), so a stack
written with :func:`from_lps` and read back with :func:`to_lps` under the
same code is voxel-identical.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["PATIENT_FRAME", "LETTERS", "parse_orientation", "axis_map", "to_lps",
           "from_lps", "lps_geometry", "image_geometry"]

#: The patient frame every case is stored in.
PATIENT_FRAME = "LPS"

#: Letter -> (LPS axis, sign): the axis a letter names and whether it runs
#: along (+1) or against (-1) that LPS axis.
LETTERS = {"L": (0, 1), "R": (0, -1), "P": (1, 1), "A": (1, -1),
           "S": (2, 1), "I": (2, -1)}
_PAIRS = ("L/R", "P/A", "S/I")


def parse_orientation(code, path: str | Path | None = None,
                      where: str | None = None) -> str:
    """Check an orientation code and return it in upper case.

    Parameters
    ----------
    code : str
        Three letters for image columns, image rows and slices, each one of
        ``L R P A S I`` (case-insensitive), one from each pair.
    path, where : optional
        File and field named by the error.

    Raises
    ------
    BonesimError
        Not a string, not three letters, an unknown letter, or an axis pair
        named twice.
    """
    hint = ("three letters for image columns, rows and slices, each naming the "
            "direction that axis increases toward (L/R, P/A, S/I), e.g. 'LPS'")
    if not isinstance(code, str):
        raise BonesimError(f"orientation must be a string of {hint}, got {code!r}",
                           path, where)
    c = code.strip().upper()
    if len(c) != 3:
        raise BonesimError(f"orientation {code!r} must be {hint}", path, where)
    for ch in c:
        if ch not in LETTERS:
            raise BonesimError(f"orientation {code!r}: {ch!r} is not one of "
                               "L, R, P, A, S, I", path, where)
    axes = [LETTERS[ch][0] for ch in c]
    for a in range(3):
        if axes.count(a) > 1:
            named = "".join(ch for ch in c if LETTERS[ch][0] == a)
            raise BonesimError(f"orientation {code!r} names the {_PAIRS[a]} axis more "
                               f"than once ({named}); each of L/R, P/A, S/I must "
                               "appear exactly once", path, where)
    return c


def axis_map(code: str) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """Which image axis feeds each LPS axis, and its sign.

    Returns
    -------
    source : (3,) int
        ``source[a]`` is the image axis (0 columns, 1 rows, 2 slices) that
        runs along LPS axis ``a``.
    sign : (3,) int
        ``+1`` when that image axis increases along ``+a``, ``-1`` against.
    """
    c = parse_orientation(code)
    source = [0, 0, 0]
    sign = [1, 1, 1]
    for i, ch in enumerate(c):
        a, s = LETTERS[ch]
        source[a] = i
        sign[a] = s
    return tuple(source), tuple(sign)


def to_lps(data: np.ndarray, code: str) -> np.ndarray:
    """Reorder an image-ordered array ``(columns, rows, slices, ...)`` into LPS.

    Returns a view (flips and a transpose only); trailing axes are kept.
    """
    source, sign = axis_map(code)
    out = np.asarray(data)
    for a in range(3):
        if sign[a] < 0:
            out = np.flip(out, axis=source[a])
    rest = tuple(range(3, out.ndim))
    return out.transpose(tuple(source) + rest)


def from_lps(data: np.ndarray, code: str) -> np.ndarray:
    """Inverse of :func:`to_lps`: an LPS array in the stack's image order."""
    source, sign = axis_map(code)
    inv = [0, 0, 0]
    for a in range(3):
        inv[source[a]] = a
    out = np.asarray(data).transpose(tuple(inv) + tuple(range(3, np.ndim(data))))
    for a in range(3):
        if sign[a] < 0:
            out = np.flip(out, axis=source[a])
    return out


def lps_geometry(code: str, shape_img, spacing_img_mm, first_center_mm
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Spacing and origin in LPS of a stack whose first voxel is known.

    Parameters
    ----------
    code : str
        The stack's orientation.
    shape_img : (3,) int
        Voxel counts along image columns, rows, slices.
    spacing_img_mm : (3,) float
        Voxel edges along image columns, rows, slices [mm].
    first_center_mm : (3,) float
        Case-frame (LPS) centre of image voxel ``(0, 0, 0)`` (first slice,
        top-left pixel) [mm].

    Returns
    -------
    spacing_mm : (3,) float64
        Voxel edges along x, y, z [mm].
    origin_mm : (3,) float64
        Case-frame centre of LPS voxel ``(0, 0, 0)`` [mm].
    """
    source, sign = axis_map(code)
    shape = np.asarray(shape_img, dtype=np.int64).reshape(3)
    sp_img = np.asarray(spacing_img_mm, dtype=np.float64).reshape(3)
    first = np.asarray(first_center_mm, dtype=np.float64).reshape(3)
    spacing = sp_img[list(source)]
    origin = first.copy()
    for a in range(3):
        if sign[a] < 0:                       # image index 0 sits at the +a end
            origin[a] -= (shape[source[a]] - 1) * spacing[a]
    return spacing, origin


def image_geometry(code: str, shape_lps, spacing_mm, origin_mm
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`lps_geometry`: image-order spacing and first centre.

    Returns
    -------
    spacing_img_mm : (3,) float64
        Voxel edges along image columns, rows, slices [mm].
    first_center_mm : (3,) float64
        Case-frame centre of image voxel ``(0, 0, 0)`` [mm].
    """
    source, sign = axis_map(code)
    shape = np.asarray(shape_lps, dtype=np.int64).reshape(3)
    spacing = np.asarray(spacing_mm, dtype=np.float64).reshape(3)
    first = np.asarray(origin_mm, dtype=np.float64).reshape(3).copy()
    sp_img = np.empty(3)
    for a in range(3):
        sp_img[source[a]] = spacing[a]
        if sign[a] < 0:
            first[a] += (shape[a] - 1) * spacing[a]
    return sp_img, first
