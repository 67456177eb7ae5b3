"""Which structure a pixel of drawn bone shows: the voxel its ray reaches.

The renderer's label pass (:mod:`bonesim.render.dataset`) tells, per pixel,
which body's surface the ray through the pixel's centre meets first and at
what depth. The bone surface's triangles join voxel centres (or points near
them), so the structure there is read from the voxels: the ray is walked
voxel by voxel (Amanatides and Woo's traversal; a voxel is the cube of edge
``spacing`` around its centre) in the body's own frame, from
:data:`BACK_VOXELS` voxels before the drawn surface to :data:`AHEAD_VOXELS`
past it, and the first voxel of that body with density > 0 gives the label.
A ray that finds none there (it grazed the surface's edge) takes the
nearest occupied voxel of the body around the hit point; ``misses`` counts
the pixels that found neither (label 0).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["BACK_VOXELS", "AHEAD_VOXELS", "first_voxel_labels"]

#: The walk starts this many voxel edges before the drawn surface ...
BACK_VOXELS = 1.5
#: ... and ends this many past it.
AHEAD_VOXELS = 2.0


@njit(cache=True, nogil=True, inline="always")
def _occupied_label(keys, vals, density, label, body, nx, ny, nz, i, j, k, b):
    """Label of voxel (i, j, k) if it is occupied and of body ``b``, else -1."""
    if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
        return -1
    br = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if br < 0:
        return -1
    off = voxel_offset(i, j, k)
    if density[br, off] <= 0.0 or body[br, off] != b:
        return -1
    return np.int64(label[br, off])


@njit(cache=True, nogil=True)
def _walk(keys, vals, density, label, body, shape, origin, h, bods, orgs, dirs, thit,
          back, ahead, out):
    nx, ny, nz = shape[0], shape[1], shape[2]
    misses = 0
    for q in range(orgs.shape[0]):
        b = bods[q]
        t0 = max(thit[q] - back * h, 0.0)
        t1 = thit[q] + ahead * h
        # continuous voxel coordinates (voxel centres at integers)
        pos = np.empty(3)
        idx = np.empty(3, np.int64)
        stp = np.empty(3, np.int64)
        tmax = np.empty(3)
        tdel = np.empty(3)
        for a in range(3):
            pos[a] = (orgs[q, a] + dirs[q, a] * t0 - origin[a]) / h
            idx[a] = np.int64(math.floor(pos[a] + 0.5))
            d = dirs[q, a]
            if d > 0.0:
                stp[a] = 1
                tmax[a] = t0 + (idx[a] + 0.5 - pos[a]) * h / d
                tdel[a] = h / d
            elif d < 0.0:
                stp[a] = -1
                tmax[a] = t0 + (idx[a] - 0.5 - pos[a]) * h / d
                tdel[a] = -h / d
            else:
                stp[a] = 0
                tmax[a] = np.inf
                tdel[a] = np.inf
        found = -1
        t = t0
        while t <= t1:
            lab = _occupied_label(keys, vals, density, label, body, nx, ny, nz,
                                  idx[0], idx[1], idx[2], b)
            if lab >= 0:
                found = lab
                break
            a = 0
            if tmax[1] < tmax[a]:
                a = 1
            if tmax[2] < tmax[a]:
                a = 2
            t = tmax[a]
            idx[a] += stp[a]
            tmax[a] += tdel[a]
        if found < 0:
            # nearest occupied voxel of the body around the hit point
            best = np.inf
            hc = np.empty(3)
            for a in range(3):
                hc[a] = (orgs[q, a] + dirs[q, a] * thit[q] - origin[a]) / h
            ci = np.int64(math.floor(hc[0] + 0.5))
            cj = np.int64(math.floor(hc[1] + 0.5))
            ck = np.int64(math.floor(hc[2] + 0.5))
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    for dk in range(-1, 2):
                        lab = _occupied_label(keys, vals, density, label, body, nx, ny, nz,
                                              ci + di, cj + dj, ck + dk, b)
                        if lab < 0:
                            continue
                        e = ((ci + di - hc[0]) ** 2 + (cj + dj - hc[1]) ** 2
                             + (ck + dk - hc[2]) ** 2)
                        if e < best:
                            best = e
                            found = lab
        if found < 0:
            misses += 1
            found = 0
        out[q] = found
    return misses


def first_voxel_labels(grid, body, bodies, origins, dirs, t_hit, back=BACK_VOXELS,
                       ahead=AHEAD_VOXELS):
    """The structure label each ray reaches near its drawn hit.

    Parameters
    ----------
    grid : Grid
        The tissue now (density, label, brick table).
    body : (n_bricks, 512) uint8
        Body id per voxel (the state's ``body``).
    bodies : (n,) int
        The body each ray hit.
    origins, dirs : (n, 3) float64
        Ray origins [mm] and unit directions, in each ray's body frame.
    t_hit : (n,) float64
        Distance along the ray to the drawn surface [mm].
    back, ahead : float
        The walk's extent before and past the hit [voxel edges].

    Returns
    -------
    labels : (n,) uint8
        0 where no voxel of the body was found.
    misses : int
        Rays that found none.
    """
    n = len(t_hit)
    out = np.zeros(n, np.int64)
    if n == 0:
        return out.astype(np.uint8), 0
    misses = _walk(grid.keys, grid.vals, grid.density, grid.label, body,
                   np.asarray(grid.shape, np.int64), np.asarray(grid.origin_mm, np.float64),
                   float(grid.spacing_mm), np.ascontiguousarray(bodies, np.int64),
                   np.ascontiguousarray(origins, np.float64),
                   np.ascontiguousarray(dirs, np.float64),
                   np.ascontiguousarray(t_hit, np.float64), float(back), float(ahead), out)
    return out.astype(np.uint8), int(misses)
