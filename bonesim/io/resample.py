"""Resampling a case-frame volume onto isotropic voxels, slab by slab.

Every volume handed to the engine is first put on an isotropic grid
(:func:`resample_isotropic`). At a source's own resolution (0.1-0.2 mm, up to
512³ voxels and more) a whole-volume temporary of the wrong type costs more
than the volume itself (a float32 copy of a 512³ label map is 512 MB, an
``intp`` one 1 GB), so everything here works on **slabs**: runs of output
planes along x small enough (:data:`SLAB_VOXELS`) that their temporaries stay
a few MB; the only whole-volume array allocated is the result.

Grid convention
---------------
The physical box, voxel edge to voxel edge, is kept. Along an axis of ``n``
source voxels of edge ``s`` [mm], the output has ``round(n * s / v)`` voxels
of edge ``v`` [mm]; output voxel ``o`` is centred at ``(o + 0.5) * v`` from
the box's low edge, i.e. at source index coordinate
``c = (o + 0.5) * v / s - 0.5``, and the new origin (centre of voxel
``(0, 0, 0)``) is ``origin - s / 2 + v / 2``. Nearest-neighbour picks the
source voxel ``floor(c + 0.5)``, linear interpolates between ``floor(c)``
and ``floor(c) + 1``; both clamp ``c`` to the source (edges repeat), as
``scipy.ndimage.affine_transform`` does with ``mode="nearest"``.
"""
from __future__ import annotations

import numpy as np

from bonesim.io.raw_volume import SPACING_RTOL

__all__ = ["SLAB_VOXELS", "SPACING_RTOL", "slabs", "label_counts", "nearest_indices",
           "linear_weights", "resample_isotropic"]

SLAB_VOXELS = 1 << 22
"""Most voxels of one slab's temporaries (4 Mi: 4 MB of uint8, 16 MB of
float32)."""

def slabs(n0: int, plane_voxels: int, budget: int | None = None):
    """Ranges ``(a, b)`` of planes along axis 0, each of at most ``budget``
    voxels (at least one plane), covering ``0 .. n0``.

    Parameters
    ----------
    n0 : int
        Planes along axis 0.
    plane_voxels : int
        Voxels of one plane (``n1 * n2``).
    budget : int, optional
        Most voxels per slab (default :data:`SLAB_VOXELS`).
    """
    budget = SLAB_VOXELS if budget is None else budget
    step = max(1, int(budget) // max(1, int(plane_voxels)))
    for a in range(0, int(n0), step):
        yield a, min(int(n0), a + step)


def label_counts(labels: np.ndarray, minlength: int = 0) -> np.ndarray:
    """Voxel count per label value, slab by slab.

    ``np.bincount`` casts its input to ``intp`` (8 bytes per voxel: 1 GB for
    a 512³ label map); this counts in slabs of :data:`SLAB_VOXELS`.

    Parameters
    ----------
    labels : (n0, n1, n2) uint8
    minlength : int
        Length of the result at least.

    Returns
    -------
    (max(minlength, labels.max() + 1),) int64
        As ``np.bincount(labels.ravel(), minlength=minlength)``.
    """
    labels = np.asarray(labels)
    counts = np.zeros(256, dtype=np.int64)
    if labels.dtype != np.uint8:
        raise ValueError(f"labels must be uint8, got {labels.dtype}")
    if labels.ndim != 3:
        labels = labels.reshape(-1, 1, 1)
    for a, b in slabs(labels.shape[0], labels.shape[1] * labels.shape[2]):
        c = np.bincount(labels[a:b].ravel(), minlength=256)
        counts[:len(c)] += c
    last = int(np.flatnonzero(counts)[-1]) + 1 if counts.any() else 0
    if minlength > 256:
        counts = np.concatenate([counts, np.zeros(int(minlength) - 256, np.int64)])
    return counts[:max(int(minlength), last)]


def nearest_indices(n_in: int, spacing_mm: float, voxel_mm: float, n_out: int
                    ) -> np.ndarray:
    """Source index of each output voxel's centre along one axis (nearest).

    Output voxel ``o`` (edge ``voxel_mm``) is centred at
    ``(o + 0.5) * voxel_mm`` from the box's low edge, which falls in source
    voxel ``floor(c + 0.5)`` with ``c = (o + 0.5) * voxel_mm / spacing_mm - 0.5``,
    clipped to the source (the box's edges repeat the edge voxels). ``c`` is
    evaluated in the floating-point order ``scipy.ndimage.affine_transform``
    uses for a diagonal matrix, so ties (a centre exactly on a voxel
    boundary) fall the same way.

    Returns
    -------
    (n_out,) intp
    """
    scale = voxel_mm / spacing_mm
    shift = (0.5 * scale - 0.5) / scale
    c = (np.arange(n_out, dtype=np.float64) + shift) * scale
    return np.clip(np.floor(c + 0.5), 0, n_in - 1).astype(np.intp)


def linear_weights(n_in: int, spacing_mm: float, voxel_mm: float, n_out: int):
    """The two source indices and the weight of the second for each output
    voxel along one axis (linear interpolation, edges repeated).

    Returns
    -------
    lo, hi : (n_out,) intp
        ``floor(c)`` and ``floor(c) + 1``, both clamped to ``0 .. n_in - 1``.
    w : (n_out,) float32
        Weight of ``hi`` (``lo`` has ``1 - w``); ``c`` as in
        :func:`nearest_indices`, clamped to the source.
    """
    scale = voxel_mm / spacing_mm
    c = np.arange(n_out, dtype=np.float64) * scale + (0.5 * scale - 0.5)
    c = np.clip(c, 0.0, n_in - 1)
    lo = np.floor(c).astype(np.intp)
    hi = np.minimum(lo + 1, n_in - 1)
    return lo, hi, (c - lo).astype(np.float32)


def _is_identity(idx: np.ndarray, n_in: int) -> bool:
    return len(idx) == n_in and bool(np.all(idx == np.arange(n_in)))


def _nearest(data, idx, out) -> None:
    """Nearest-neighbour gather of ``data`` at ``idx`` (one index array per
    axis) into ``out``, slab by slab along x."""
    keep = [_is_identity(ix, n) for ix, n in zip(idx, data.shape)]
    plane = max(data.shape[1] * data.shape[2], out.shape[1] * out.shape[2])
    for a, b in slabs(out.shape[0], plane):
        block = data[a:b] if keep[0] else data[idx[0][a:b]]
        if not keep[1]:
            block = np.take(block, idx[1], axis=1)
        if keep[2]:
            out[a:b] = block
        else:
            np.take(block, idx[2], axis=2, out=out[a:b])


def _lerp(block, lo, hi, w, axis: int) -> np.ndarray:
    """Linear interpolation of a float32 ``block`` along ``axis``."""
    shape = [1, 1, 1]
    shape[axis] = -1
    wb = w.reshape(shape)
    a = np.take(block, lo, axis=axis)
    a *= 1.0 - wb
    a += np.take(block, hi, axis=axis) * wb
    return a


def _linear(data, weights, out) -> None:
    """Trilinear resampling (separable: x, then y, then z) into ``out``,
    slab by slab along x; integer outputs are rounded and clipped to their
    type. ``weights[a]`` is :func:`linear_weights` of axis ``a``, or None
    for an axis kept as it is."""
    plane = max(data.shape[1] * data.shape[2], out.shape[1] * out.shape[2])
    info = np.iinfo(out.dtype) if np.issubdtype(out.dtype, np.integer) else None
    for a, b in slabs(out.shape[0], plane, SLAB_VOXELS // 4):
        if weights[0] is None:
            block = data[a:b].astype(np.float32)
        else:
            lo0, hi0, w0 = weights[0]
            first, last = int(lo0[a:b].min()), int(hi0[a:b].max())
            block = data[first:last + 1].astype(np.float32)
            block = _lerp(block, lo0[a:b] - first, hi0[a:b] - first, w0[a:b], 0)
        for axis in (1, 2):
            if weights[axis] is not None:
                block = _lerp(block, *weights[axis], axis)
        if info is not None:
            np.rint(block, out=block)
            np.clip(block, info.min, info.max, out=block)
        out[a:b] = block


def resample_isotropic(data: np.ndarray, spacing_mm, origin_mm, voxel_mm: float,
                       order: int) -> tuple[np.ndarray, np.ndarray]:
    """Resample onto isotropic voxels of edge ``voxel_mm`` covering the same box.

    The physical box (voxel edge to voxel edge) is kept; the new voxel count
    per axis is ``round(n * spacing / voxel_mm)`` (see the module's grid
    convention). When every spacing already equals ``voxel_mm`` the data are
    returned untouched (the same array, no copy). Axes whose spacing equals
    ``voxel_mm`` are not touched either. Both orders work slab by slab along
    x: the result is the only whole-volume array allocated.

    Parameters
    ----------
    data : (nx, ny, nz) array
        Axes along x, y, z of the case frame.
    spacing_mm : (3,) float
        Current voxel edges [mm].
    origin_mm : (3,) float
        Current centre of voxel (0, 0, 0) [mm].
    voxel_mm : float
        Target edge [mm].
    order : int
        0: nearest neighbour (labels; the same result as
        ``scipy.ndimage.affine_transform`` of order 0 with ``mode="nearest"``),
        read axis by axis so only the kept voxels are read. 1: trilinear
        (intensities), computed in float32; the result keeps an integer
        ``data``'s type (rounded, clipped to it), float data give float32.

    Returns
    -------
    data : (mx, my, mz) array
        C-contiguous.
    origin_mm : (3,) float64
    """
    spacing = np.asarray(spacing_mm, dtype=np.float64).reshape(3)
    origin = np.asarray(origin_mm, dtype=np.float64).reshape(3)
    if order not in (0, 1):
        raise ValueError(f"order must be 0 or 1, got {order}")
    if np.allclose(spacing, voxel_mm, rtol=SPACING_RTOL, atol=0.0):
        return data, origin
    data = np.asarray(data)
    shape = [int(n) for n in
             np.maximum(1, np.round(np.asarray(data.shape) * spacing / voxel_mm))]
    # an axis already at voxel_mm keeps its voxels (identity indices)
    same = np.isclose(spacing, voxel_mm, rtol=SPACING_RTOL, atol=0.0)
    new_origin = origin - spacing / 2 + voxel_mm / 2
    if order == 0:
        out = np.empty(shape, dtype=data.dtype)
        idx = [np.arange(data.shape[a]) if same[a] else
               nearest_indices(data.shape[a], spacing[a], voxel_mm, shape[a])
               for a in range(3)]
        _nearest(data, idx, out)
        return out, new_origin
    dtype = data.dtype if np.issubdtype(data.dtype, np.integer) else np.float32
    out = np.empty(shape, dtype=dtype)
    weights = [None if same[a] else
               linear_weights(data.shape[a], spacing[a], voxel_mm, shape[a])
               for a in range(3)]
    _linear(data, weights, out)
    return out, new_origin
