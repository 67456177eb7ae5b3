"""Which structure a pixel of drawn bone shows: the voxel its ray reaches.

The renderer's label pass (:mod:`bonesim.render.dataset`) tells, per pixel,
which body's surface (or which structure's own mesh, drawn with the main
body) the ray through the pixel's centre meets first and at what depth. The
drawn tissue lies within about a voxel of the voxels it was made from (the
bone surface's vertices near voxel centres, a structure's smoothed mesh
around its voxels), so the structure there is read from the voxels: the ray is walked
voxel by voxel (Amanatides and Woo's traversal; a voxel is the cube of edge
``spacing`` around its centre) in the body's own frame, from
:data:`BACK_VOXELS` voxels before the drawn surface to :data:`AHEAD_VOXELS`
past it, and the first voxel of that body with density > 0 gives the label.
A ray that finds none there (it grazed the surface's edge) takes the
nearest occupied voxel of the body around the hit point; a structure's mesh
where its voxels were drilled away keeps the structure's label; ``misses``
counts the pixels that found none of these (label 0).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["BACK_VOXELS", "AHEAD_VOXELS", "first_voxel_labels", "label_image"]

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


@njit(cache=True, nogil=True, inline="always")
def _axis_start(p, d, t0, h):
    """Voxel index, step, first boundary crossing and crossing interval along one
    axis of a ray at ``t0`` (``p``: continuous voxel coordinate there)."""
    i = np.int64(math.floor(p + 0.5))
    if d > 0.0:
        return i, np.int64(1), t0 + (i + 0.5 - p) * h / d, h / d
    if d < 0.0:
        return i, np.int64(-1), t0 + (i - 0.5 - p) * h / d, -h / d
    return i, np.int64(0), np.inf, np.inf


@njit(cache=True, nogil=True)
def _walk_one(keys, vals, density, label, body, nx, ny, nz, ox, oy, oz, h, b,
              rx, ry, rz, dx, dy, dz, thit, back, ahead):
    """Label of the first voxel of body ``b`` along the ray ``r + t d`` for
    ``t`` in ``[thit - back h, thit + ahead h]``, else of the nearest such
    voxel around the hit; -1 if none."""
    t0 = max(thit - back * h, 0.0)
    t1 = thit + ahead * h
    i, si, ti, di = _axis_start((rx + dx * t0 - ox) / h, dx, t0, h)
    j, sj, tj, dj = _axis_start((ry + dy * t0 - oy) / h, dy, t0, h)
    k, sk, tk, dk = _axis_start((rz + dz * t0 - oz) / h, dz, t0, h)
    t = t0
    while t <= t1:
        lab = _occupied_label(keys, vals, density, label, body, nx, ny, nz, i, j, k, b)
        if lab >= 0:
            return lab
        if ti <= tj and ti <= tk:
            t = ti
            i += si
            ti += di
        elif tj <= tk:
            t = tj
            j += sj
            tj += dj
        else:
            t = tk
            k += sk
            tk += dk
    # nearest occupied voxel of the body around the hit point
    hx = (rx + dx * thit - ox) / h
    hy = (ry + dy * thit - oy) / h
    hz = (rz + dz * thit - oz) / h
    ci = np.int64(math.floor(hx + 0.5))
    cj = np.int64(math.floor(hy + 0.5))
    ck = np.int64(math.floor(hz + 0.5))
    best = np.inf
    found = np.int64(-1)
    for a in range(-1, 2):
        for bb in range(-1, 2):
            for c in range(-1, 2):
                lab = _occupied_label(keys, vals, density, label, body, nx, ny, nz,
                                      ci + a, cj + bb, ck + c, b)
                if lab < 0:
                    continue
                e = (ci + a - hx) ** 2 + (cj + bb - hy) ** 2 + (ck + c - hz) ** 2
                if e < best:
                    best = e
                    found = lab
    return found


@njit(cache=True, nogil=True)
def _walk(keys, vals, density, label, body, shape, origin, h, bods, orgs, dirs, thit,
          back, ahead, out):
    misses = 0
    for q in range(orgs.shape[0]):
        lab = _walk_one(keys, vals, density, label, body, shape[0], shape[1], shape[2],
                        origin[0], origin[1], origin[2], h, bods[q], orgs[q, 0], orgs[q, 1],
                        orgs[q, 2], dirs[q, 0], dirs[q, 1], dirs[q, 2], thit[q], back, ahead)
        if lab < 0:
            misses += 1
            lab = 0
        out[q] = lab
    return misses


@njit(cache=True, nogil=True)
def _label_image(keys, vals, density, label, body, shape, origin, h, entry_body,
                 entry_fallback, idx, depth, kinv, rot, eye, pose_m, back, ahead, out):
    """Every pixel whose entry is tissue (``entry_body[idx] >= 0``): its ray from
    ``eye`` through the pixel centre, taken into that body's frame."""
    misses = 0
    for v in range(idx.shape[0]):
        for u in range(idx.shape[1]):
            b = entry_body[idx[v, u]]
            z = depth[v, u]
            if b < 0 or not np.isfinite(z):
                continue
            # camera-frame ray (z = 1), then the case frame (R.T) and unit length
            cx = kinv[0, 0] * u + kinv[0, 2]
            cy = kinv[1, 1] * v + kinv[1, 2]
            n = math.sqrt(cx * cx + cy * cy + 1.0)
            wx = (rot[0, 0] * cx + rot[1, 0] * cy + rot[2, 0]) / n
            wy = (rot[0, 1] * cx + rot[1, 1] * cy + rot[2, 1]) / n
            wz = (rot[0, 2] * cx + rot[1, 2] * cy + rot[2, 2]) / n
            # into the body's frame: x_body = Rb.T (x_case - tb)
            ex = eye[0] - pose_m[b, 0, 3]
            ey = eye[1] - pose_m[b, 1, 3]
            ez = eye[2] - pose_m[b, 2, 3]
            rx = pose_m[b, 0, 0] * ex + pose_m[b, 1, 0] * ey + pose_m[b, 2, 0] * ez
            ry = pose_m[b, 0, 1] * ex + pose_m[b, 1, 1] * ey + pose_m[b, 2, 1] * ez
            rz = pose_m[b, 0, 2] * ex + pose_m[b, 1, 2] * ey + pose_m[b, 2, 2] * ez
            dx = pose_m[b, 0, 0] * wx + pose_m[b, 1, 0] * wy + pose_m[b, 2, 0] * wz
            dy = pose_m[b, 0, 1] * wx + pose_m[b, 1, 1] * wy + pose_m[b, 2, 1] * wz
            dz = pose_m[b, 0, 2] * wx + pose_m[b, 1, 2] * wy + pose_m[b, 2, 2] * wz
            lab = _walk_one(keys, vals, density, label, body, shape[0], shape[1], shape[2],
                            origin[0], origin[1], origin[2], h, b, rx, ry, rz, dx, dy, dz,
                            z * n, back, ahead)
            if lab < 0:
                lab = entry_fallback[idx[v, u]]
                if lab == 0:
                    misses += 1
            out[v, u] = lab
    return misses


def label_image(grid, body, pose_m, entry_body, idx, depth, k, r, eye, out,
                entry_fallback=None, back=BACK_VOXELS, ahead=AHEAD_VOXELS) -> int:
    """Label the tissue pixels of a frame in place.

    Parameters
    ----------
    grid, body
        As :func:`first_voxel_labels`.
    pose_m : (max_bodies, 3, 4) float64
        Body-to-case poses (the state's ``pose_m``).
    entry_body : (n_entries,) int64
        The body each entry of the label pass shows, -1 for entries that are
        not tissue (a body's surface, or a structure's own mesh: body 0).
    idx : (H, W) int64
        Entry per pixel.
    depth : (H, W) float32
        Depth along the optical axis [mm].
    k, r, eye
        Intrinsics, extrinsics' rotation (case -> camera, OpenCV) and the
        eye [mm] (:mod:`bonesim.session.dataset_camera`).
    out : (H, W) uint8
        Receives the labels of those pixels (others untouched).
    entry_fallback : (n_entries,) uint8, optional
        The label a pixel of the entry takes when its ray finds no voxel (a
        structure's mesh: its structure, where its voxels were drilled
        away); 0 (default) counts it as a miss.

    Returns
    -------
    int
        Pixels whose ray found no voxel of their body and have no fallback
        (labelled 0).
    """
    n = len(entry_body)
    fb = np.zeros(n, np.uint8) if entry_fallback is None else entry_fallback
    return int(_label_image(grid.keys, grid.vals, grid.density, grid.label, body,
                            np.asarray(grid.shape, np.int64),
                            np.asarray(grid.origin_mm, np.float64), float(grid.spacing_mm),
                            np.ascontiguousarray(entry_body, np.int64),
                            np.ascontiguousarray(fb, np.uint8),
                            np.ascontiguousarray(idx, np.int64),
                            np.ascontiguousarray(depth, np.float32),
                            np.linalg.inv(np.asarray(k, np.float64)),
                            np.ascontiguousarray(r, np.float64),
                            np.ascontiguousarray(eye, np.float64),
                            np.ascontiguousarray(pose_m, np.float64), float(back), float(ahead),
                            out))


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
