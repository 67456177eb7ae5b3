"""The reader-side volume record and the snap of a file's axes onto LPS.

Readers of every format (:mod:`bonesim.io.dicom`, :mod:`bonesim.io.images`,
:mod:`bonesim.io.label_stack`, :mod:`bonesim.io.segmentation`) turn one file or
folder into a :class:`RawVolume` whose axes already run along ``+x, +y, +z`` of
the LPS patient frame (flips and permutations only, never interpolated);
:func:`bonesim.io.volumes.load_volume` then labels and resamples it.

An **oblique** volume (direction cosines not aligned with the case axes) is
reordered onto the nearest axes and its residual rotation is dropped; an
:class:`ObliqueWarning` says so and by how many degrees.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["MAX_STRUCTURES", "SPACING_RTOL", "OBLIQUE_TOL", "GRID_TOL_MM", "MAX_LISTED",
           "LPS_FROM_RAS", "ObliqueWarning", "RawVolume", "snap_to_lps", "check_file",
           "squeeze3"]

MAX_STRUCTURES = 255
"""Structure indices are stored as uint8 (0 is empty)."""

SPACING_RTOL = 1e-6
"""Relative tolerance under which a spacing counts as equal to ``voxel_mm``."""

OBLIQUE_TOL = 1e-4
"""Largest direction-cosine deviation still treated as axis-aligned."""

GRID_TOL_MM = 1e-3
"""Tolerance when checking that a label map shares its volume's grid [mm]."""

MAX_LISTED = 8
"""How many offending items (colours, values, files) an error message lists."""


#: Row flip taking RAS coordinates (NIfTI, some NRRD) to LPS.
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])


class ObliqueWarning(UserWarning):
    """A volume's axes were snapped to the nearest case-frame axes."""


@dataclass
class RawVolume:
    """One file's data, axes already along ``+x, +y, +z`` of the case frame.

    Attributes
    ----------
    data : (nx, ny, nz) array
        Intensities (readers of CT formats) or structure indices (label stack).
    spacing_mm : (3,) float64
        Voxel edge along x, y, z [mm]; may be anisotropic.
    origin_mm : (3,) float64
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    source : str
        The file or folder read, with its format.
    """

    data: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    source: str


def snap_to_lps(data: np.ndarray, affine: np.ndarray, path: Path, source: str
                 ) -> RawVolume:
    """Reorder ``data`` so its axes run along +x, +y, +z (LPS).

    Parameters
    ----------
    data : (n0, n1, n2) array
        Voxel data in file index order.
    affine : (4, 4) float
        Index -> case-frame (LPS) position [mm] of voxel centres.
    path : Path
        File or folder, for messages.
    source : str
        Description kept in the result.
    """
    from nibabel.orientations import (apply_orientation, inv_ornt_aff,
                                      io_orientation, ornt_transform)

    affine = np.asarray(affine, dtype=np.float64)
    cols = affine[:3, :3]
    norms = np.linalg.norm(cols, axis=0)
    if not np.all(np.isfinite(affine)) or np.any(norms <= 0):
        raise BonesimError("missing or invalid voxel spacing / orientation "
                           f"(axis lengths {np.round(norms, 6).tolist()} mm)", path)
    ornt = io_orientation(affine)
    if np.isnan(ornt).any():
        raise BonesimError("degenerate orientation: two axes point the same way", path)
    to_lps = ornt_transform(ornt, np.array([[0, 1], [1, 1], [2, 1]]))
    out = apply_orientation(data, to_lps)
    aff = affine @ inv_ornt_aff(to_lps, data.shape)
    spacing = np.linalg.norm(aff[:3, :3], axis=0)
    dirs = aff[:3, :3] / spacing
    dev = np.abs(dirs - np.eye(3)).max()
    if dev > OBLIQUE_TOL:
        angle = np.degrees(np.arccos(np.clip(np.diag(dirs).min(), -1.0, 1.0)))
        warnings.warn(f"{path}: volume is oblique (up to {angle:.1f} deg off the "
                      "case axes); its axes were snapped to the nearest case axes "
                      "without resampling", ObliqueWarning, stacklevel=3)
    return RawVolume(np.ascontiguousarray(out), spacing, aff[:3, 3].copy(), source)


def check_file(path: Path, what: str) -> None:
    """Raise a :class:`BonesimError` unless ``path`` is an existing file."""
    if not path.exists():
        raise BonesimError(f"{what} file not found", path)
    if not path.is_file():
        raise BonesimError(f"expected a {what} file, got a folder", path)


def squeeze3(data: np.ndarray, path: Path) -> np.ndarray:
    """Drop trailing length-1 axes; the result must be 3-D (error names ``path``)."""
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise BonesimError(f"expected a 3-D volume, got shape {data.shape}", path)
    return data
