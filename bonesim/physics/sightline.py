"""How deep the burr is buried: tissue between the burr and the eye.

When the burr bores into bone it leaves the surgeon's sight. The window
then draws it as a silhouette through the bone and the HUD gives its depth
below the surface; this module measures that depth.

:func:`depth_below_surface_mm` follows the line of sight from the point of
the burr nearest the eye (``pos + radius * u``, ``u`` the unit vector from
the burr centre toward the eye) to the eye, and adds up the length of that
segment lying inside occupied voxels (density > 0: bone and every structure
alike, since any of them hides the burr). Voxel ``(i, j, k)`` is the cube of
edge ``spacing_mm`` centred on ``origin_mm + spacing_mm * (i, j, k)``
(:mod:`bonesim.engine.grid`'s lattice, case frame LPS [mm]).

The segment is traversed exactly, voxel by voxel (Amanatides and Woo's
3-D DDA): the result is the sum of exact chord lengths, not a sampled
approximation, so a slab ``N`` voxels thick crossed at an angle ``theta``
to its normal gives ``N * spacing_mm / cos(theta)`` to rounding. The segment
is first clipped to the grid's volume (outside it nothing is occupied), so
a far eye costs nothing. Brick lookups are cached along the ray (one hash
probe per brick entered). Cost: one step per voxel crossed, about 0.2 us
each; a 60 mm sight line at 0.5 mm voxels takes a few tens of microseconds.

The grid is read without locks: a voxel removed meanwhile changes one chord,
never crashes.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["depth_below_surface_mm", "sightline_kernel", "warmup"]

# "no brick cached yet" marker of the ray's brick cache
_NO_BRICK = -2
# a direction component smaller than this counts as parallel to the axis
_PARALLEL = 1e-12


@njit(cache=True, nogil=True)
def _sightline(keys, vals, density, origin, h, shape, px, py, pz, dx, dy, dz, length):
    """Length [mm] of the segment ``p + t d``, ``0 <= t <= length`` [mm]
    (``d`` a unit vector) inside voxels with density > 0."""
    # voxel coordinates shifted by 1/2: voxel i spans [i, i + 1)
    q = np.empty(3)
    d = np.empty(3)
    q[0] = (px - origin[0]) / h + 0.5
    q[1] = (py - origin[1]) / h + 0.5
    q[2] = (pz - origin[2]) / h + 0.5
    d[0] = dx
    d[1] = dy
    d[2] = dz
    # clip to the volume [0, shape) (in the shifted coordinates) [mm of t]
    t0 = 0.0
    t1 = length
    for a in range(3):
        if abs(d[a]) < _PARALLEL:
            if q[a] < 0.0 or q[a] >= shape[a]:
                return 0.0
            continue
        ta = (0.0 - q[a]) * h / d[a]
        tb = (shape[a] - q[a]) * h / d[a]
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
    if t1 <= t0:
        return 0.0
    # DDA from the clipped start
    cell = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    tmax = np.empty(3)
    tdelta = np.empty(3)
    for a in range(3):
        qa = q[a] + d[a] * t0 / h
        c = int(math.floor(qa))
        if c < 0:
            c = 0
        if c > shape[a] - 1:
            c = shape[a] - 1
        cell[a] = c
        if abs(d[a]) < _PARALLEL:
            step[a] = 0
            tmax[a] = math.inf
            tdelta[a] = math.inf
        elif d[a] > 0:
            step[a] = 1
            tmax[a] = (c + 1 - q[a]) * h / d[a]
            tdelta[a] = h / d[a]
        else:
            step[a] = -1
            tmax[a] = (c - q[a]) * h / d[a]
            tdelta[a] = -h / d[a]
    total = 0.0
    t = t0
    cb = np.int64(_NO_BRICK)
    cbi = cbj = cbk = np.int64(0)
    while t < t1:
        # leave the current cell at the nearest boundary
        a = 0
        if tmax[1] < tmax[a]:
            a = 1
        if tmax[2] < tmax[a]:
            a = 2
        tn = tmax[a]
        if tn > t1:
            tn = t1
        i, j, k = cell[0], cell[1], cell[2]
        bi, bj, bk = i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT
        if cb == _NO_BRICK or bi != cbi or bj != cbj or bk != cbk:
            cb = find_brick(keys, vals, bi, bj, bk)
            cbi, cbj, cbk = bi, bj, bk
        if cb >= 0 and density[cb, voxel_offset(i, j, k)] > 0.0 and tn > t:
            total += tn - t
        t = tn
        cell[a] += step[a]
        tmax[a] += tdelta[a]
        if cell[a] < 0 or cell[a] >= shape[a]:
            break
    return total


def sightline_kernel():
    """The numba kernel behind :func:`depth_below_surface_mm` (for callers
    that inline it in their own kernels). Signature::

        _sightline(keys, vals, density, origin (3,) f8, h, shape (3,) i8,
                   px, py, pz, dx, dy, dz, length) -> float [mm]
    """
    return _sightline


def _vec3(v, name) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be 3 finite numbers [mm], got {v!r}")
    return a


def depth_below_surface_mm(grid, pos_mm, eye_mm, radius_mm) -> float:
    """Tissue between the burr's surface and the eye along the line of sight.

    Parameters
    ----------
    grid : bonesim.engine.grid.Grid
        The current tissue (voxels with density > 0 hide the burr).
    pos_mm : (3,) float
        Burr centre, case frame LPS [mm].
    eye_mm : (3,) float
        The eye (the camera position), case frame LPS [mm].
    radius_mm : float
        Burr radius [mm], >= 0.

    Returns
    -------
    float
        Length [mm] of the straight segment from ``pos + radius * u`` to the
        eye (``u`` the unit vector toward the eye) that lies inside occupied
        voxels; 0.0 when nothing covers the burr, or the eye is inside it.

    Raises
    ------
    ValueError
        On non-finite positions or a negative radius.
    """
    p = _vec3(pos_mm, "pos_mm")
    e = _vec3(eye_mm, "eye_mm")
    r = float(radius_mm)
    if not (math.isfinite(r) and r >= 0):
        raise ValueError(f"radius_mm must be finite and >= 0, got {radius_mm!r}")
    v = e - p
    dist = float(np.linalg.norm(v))
    if dist <= r:
        return 0.0
    u = v / dist
    s = p + r * u
    shape = np.asarray(grid.shape, dtype=np.int64)
    return float(_sightline(grid.keys, grid.vals, grid.density, grid.origin_mm,
                            float(grid.spacing_mm), shape, s[0], s[1], s[2],
                            u[0], u[1], u[2], dist - r))


def warmup() -> None:
    """Compile (or load from the cache) the kernel."""
    from bonesim.engine.grid import Grid

    lab = np.zeros((8, 8, 8), np.uint8)
    lab[:, :, :4] = 1
    g = Grid.from_dense(lab, spacing_mm=0.5)
    depth_below_surface_mm(g, (2.0, 2.0, 0.5), (2.0, 2.0, 50.0), 0.5)
