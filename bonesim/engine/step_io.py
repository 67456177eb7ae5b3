"""The haptic step's checks of a sample and its bookkeeping afterwards, each
one compiled call (:func:`bonesim.engine.model.step`).

At 1 kHz the Python around the step's kernel is a good part of its cost: a
handful of small numpy operations on (3,) vectors (norm, finiteness,
normalisation; the counts, pose and force kept in the state) take a few
microseconds between them. These two kernels do the same float operations in
the same order (IEEE square root and division, as numpy and Python do), so
the state they leave is the same bits.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["unit_pose", "store_step"]


@njit(cache=True, nogil=True)
def unit_pose(pos, ax):
    """Check a sample's position and normalise its axis in place.

    Parameters
    ----------
    pos : (3,) float64
        Tool centre, case frame [mm].
    ax : (3,) float64
        Drill axis (any length); made unit length in place.

    Returns
    -------
    bool
        False (``ax`` left as it is) where the position is not finite or the
        axis has no finite, non-zero length.
    """
    norm = np.sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2])
    if not norm > 0.0 or not np.isfinite(norm):
        return False
    if not (np.isfinite(pos[0]) and np.isfinite(pos[1]) and np.isfinite(pos[2])):
        return False
    for q in range(3):
        ax[q] = ax[q] / norm
    return True


@njit(cache=True, nogil=True)
def store_step(removed_by_label, lost, pos_mm, pos, axis, ax, force_n, out):
    """A step's bookkeeping: ``removed_by_label += lost`` (voxels per label),
    the tool's position [mm] and unit axis, and the force [N] (``out[:3]``)."""
    for q in range(removed_by_label.shape[0]):
        removed_by_label[q] += lost[q]
    for q in range(3):
        pos_mm[q] = pos[q]
        axis[q] = ax[q]
        force_n[q] = out[q]
