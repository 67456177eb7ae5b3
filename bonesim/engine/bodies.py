"""Bone as bodies: a body id per voxel and a rigid pose per body.

A case's bone is a set of **bodies**. The :class:`~bonesim.engine.model.Model` fixes
the most bodies a run may hold (``max_bodies``, default
:data:`DEFAULT_MAX_BODIES`), so that every per-body array has a fixed size and
shared memory never grows while the haptic loop runs. The
:class:`~bonesim.engine.model.State` holds

``body`` (n_bricks, 512) uint8
    the body id of every voxel, laid out like the grid's density;
``pose`` (max_bodies, 7) float64
    each body's rigid transform from its own frame to the case frame,
    ``(tx, ty, tz [mm], qw, qx, qy, qz)`` with a unit quaternion;
``pose_m`` (max_bodies, 3, 4) float64
    the same transform as a matrix ``[R | t]``, derived from ``pose`` by
    :func:`pose_matrix` (the one place it is computed, so every process
    derives identical bits);
``alive`` (max_bodies,) uint8
    1 for the bodies that exist;
``bounds`` (max_bodies, 6) int32
    each body's voxel box in its own frame, ``(i0, j0, k0, i1, j1, k1)``
    inclusive (conservative: it may be larger than the body).

A body's voxels never move in the grid: a voxel ``(i, j, k)`` of body ``b``
lies at ``R_b (origin + spacing * (i, j, k)) + t_b`` in the case frame. The
haptic step transforms the tool into each nearby body's frame instead (one
pass per group of bodies with the same pose, see :func:`plan_passes`), so a
case that is one body with the identity pose steps exactly as before bodies
existed.

Bodies come into being by :func:`split_body` (a set of voxels of one body
becomes a new body) and move by :func:`set_pose`; both are applied through
the haptic loop's command ring and published as ``SPLIT`` / ``POSE`` tissue
events (:mod:`bonesim.engine.events`), so every replica applies them in order.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from bonesim.engine.events import POSE, SPLIT, push_event
from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.haptics import push_event_kernel
from bonesim.engine.kernel_args import read_only

__all__ = ["DEFAULT_MAX_BODIES", "BODY_LIMIT", "IDENTITY_POSE", "body_arrays_spec",
           "init_bodies", "pose_matrix", "is_identity", "validate_pose", "plan_passes",
           "split_body", "set_pose", "publish_split", "publish_split_box", "publish_pose",
           "body_voxel_counts", "to_body_frame", "to_case_frame", "posed_bodies",
           "Bodies", "all_identity", "pose_groups", "voxel_bodies", "majority_bodies",
           "near_body_box"]

#: Bodies a model holds unless configured otherwise.
DEFAULT_MAX_BODIES = 64
#: Body ids are stored as uint8.
BODY_LIMIT = 255
#: ``(tx, ty, tz, qw, qx, qy, qz)`` of the identity transform.
IDENTITY_POSE = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
# a pose's quaternion must be unit to this tolerance
_UNIT_TOL = 1e-9


def body_arrays_spec(n_bricks: int, max_bodies: int) -> list:
    """``(name, shape, dtype)`` of the per-body state arrays (shared memory)."""
    return [("body", (n_bricks, 512), np.uint8),
            ("pose", (max_bodies, 7), np.float64),
            ("pose_m", (max_bodies, 3, 4), np.float64),
            ("alive", (max_bodies,), np.uint8),
            ("bounds", (max_bodies, 6), np.int32)]


def init_bodies(body, pose, pose_m, alive, bounds, shape) -> None:
    """One body (id 0) holding every voxel, at the identity pose, in place.

    Parameters
    ----------
    shape : (3,) int
        Grid shape [voxels]; body 0's bounds.
    """
    body[:] = 0
    pose[:] = IDENTITY_POSE
    for b in range(pose.shape[0]):
        pose_m[b] = pose_matrix(pose[b])
    alive[:] = 0
    alive[0] = 1
    bounds[:] = 0
    bounds[0, 3:] = np.asarray(shape, dtype=np.int64) - 1


def pose_matrix(pose) -> np.ndarray:
    """The (3, 4) matrix ``[R | t]`` of a pose ``(tx, ty, tz, qw, qx, qy, qz)``."""
    tx, ty, tz, w, x, y, z = (float(v) for v in pose)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y), tx],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x), ty],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y), tz]])


def is_identity(pose) -> bool:
    """True for exactly the identity pose."""
    return tuple(float(v) for v in pose) == IDENTITY_POSE


def validate_pose(pose) -> np.ndarray:
    """A pose as (7,) float64, or ValueError naming what is wrong."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (7,):
        raise ValueError(f"a body pose is (tx, ty, tz, qw, qx, qy, qz), got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"body pose {p.tolist()} is not finite")
    qn = math.sqrt(float(p[3:] @ p[3:]))
    if abs(qn - 1.0) > _UNIT_TOL:
        raise ValueError(f"body pose quaternion {p[3:].tolist()} is not unit (norm {qn})")
    return p


@njit(cache=True, nogil=True, inline="always")
def near_body_box(pose_m, bounds, b, pos, r_vox, origin, spacing) -> bool:
    """Whether the point ``pos`` (case frame [mm]) lies within ``r_vox``
    voxels of body ``b``'s voxel box (its own frame: ``R^T (pos - t)``)."""
    dx = pos[0] - pose_m[b, 0, 3]
    dy = pos[1] - pose_m[b, 1, 3]
    dz = pos[2] - pose_m[b, 2, 3]
    near = True
    for a in range(3):
        p = pose_m[b, 0, a] * dx + pose_m[b, 1, a] * dy + pose_m[b, 2, a] * dz
        v = (p - origin[a]) / spacing
        if v + r_vox < bounds[b, a] or v - r_vox > bounds[b, 3 + a]:
            near = False
    return near


@njit(cache=True, nogil=True)
def _plan(alive, pose, pose_m, bounds, pos, radius, origin, spacing, group, pass_body,
          pass_ident):
    n_pass = 0
    for b in range(alive.shape[0]):
        group[b] = -1
        if alive[b] == 0:
            continue
        if not near_body_box(pose_m, bounds, b, pos, radius / spacing + 2.0, origin, spacing):
            continue
        g = -1
        for q in range(n_pass):
            rb = pass_body[q]
            same = True
            for c in range(7):
                if pose[rb, c] != pose[b, c]:
                    same = False
            if same:
                g = q
                break
        if g < 0:
            g = n_pass
            pass_body[n_pass] = b
            pass_ident[n_pass] = (pose[b, 0] == 0.0 and pose[b, 1] == 0.0
                                  and pose[b, 2] == 0.0 and pose[b, 3] == 1.0
                                  and pose[b, 4] == 0.0 and pose[b, 5] == 0.0
                                  and pose[b, 6] == 0.0)
            n_pass += 1
        group[b] = g
    return n_pass


def plan_passes(alive, pose, pose_m, bounds, pos, radius, origin, spacing, group,
                pass_body, pass_ident) -> int:
    """Group the bodies near the tool by pose: one haptic pass per group.

    Parameters
    ----------
    alive, pose, pose_m, bounds : arrays
        The state's body arrays (see the module docstring).
    pos : (3,) float64
        Tool centre, case frame [mm].
    radius : float
        Burr radius [mm].
    origin : (3,) float64
        Centre of voxel (0, 0, 0) in a body's own frame [mm].
    spacing : float
        Voxel edge [mm].
    group : (max_bodies,) int32
        Out: the pass of each body, -1 for bodies out of reach.
    pass_body : (max_bodies,) int32
        Out: a representative body per pass (its pose is the pass's frame).
    pass_ident : (max_bodies,) bool
        Out: True where the pass's pose is exactly the identity.

    Returns
    -------
    n_pass : int
    """
    return _plan(alive, pose, pose_m, bounds, pos, float(radius), origin, float(spacing),
                 group, pass_body, pass_ident)


@njit(cache=True, nogil=True)
def _split(keys, vals, body, density, ijk, src, dst, bounds, grow):
    n = 0
    lo0 = lo1 = lo2 = 2 ** 30
    hi0 = hi1 = hi2 = -2 ** 30
    if grow:
        lo0, lo1, lo2 = bounds[dst, 0], bounds[dst, 1], bounds[dst, 2]
        hi0, hi1, hi2 = bounds[dst, 3], bounds[dst, 4], bounds[dst, 5]
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b < 0:
            continue
        off = voxel_offset(i, j, k)
        if body[b, off] != src or density[b, off] <= 0.0:
            continue
        body[b, off] = dst
        n += 1
        lo0, lo1, lo2 = min(lo0, i), min(lo1, j), min(lo2, k)
        hi0, hi1, hi2 = max(hi0, i), max(hi1, j), max(hi2, k)
    if n > 0:
        bounds[dst, 0], bounds[dst, 1], bounds[dst, 2] = lo0, lo1, lo2
        bounds[dst, 3], bounds[dst, 4], bounds[dst, 5] = hi0, hi1, hi2
    return n


def split_body(state, src: int, ijk: np.ndarray, dst: int | None = None,
               grow: bool = False) -> tuple[int, int]:
    """Make the voxels ``ijk`` of body ``src`` a new body, in place.

    Only voxels that belong to ``src`` and still hold material move; the new
    body starts at ``src``'s pose, so nothing moves in the case frame.

    Parameters
    ----------
    state : State
    src : int
        The body to split.
    ijk : (n, 3) int
        Voxels in ``src``'s frame.
    dst : int, optional
        The new body's id (default: the lowest free id). Replicas pass the id
        the haptic loop chose.
    grow : bool
        ``dst`` exists already and takes further voxels (a split published
        in several blocks).

    Returns
    -------
    dst, n : int
        The new body and how many voxels it took.

    Raises
    ------
    ValueError
        ``src`` is not a body, ``dst`` is taken, or no id is free.
    """
    alive = state.alive
    if not 0 <= src < len(alive) or not alive[src]:
        raise ValueError(f"split: body {src} does not exist")
    if dst is None:
        free = np.flatnonzero(alive == 0)
        if len(free) == 0:
            raise ValueError(f"split: all {len(alive)} bodies are in use (max_bodies)")
        dst = int(free[0])
    elif not 0 <= dst < len(alive) or bool(alive[dst]) != grow or dst == src:
        raise ValueError(f"split: body id {dst} is {'not ' if grow else ''}in use or out "
                         f"of range 0..{len(alive) - 1}")
    ijk = np.ascontiguousarray(np.asarray(ijk, dtype=np.int32).reshape(-1, 3))
    g = state.grid
    n = _split(g.keys, g.vals, state.body, g.density, read_only(ijk), np.uint8(src),
               np.uint8(dst), state.bounds, grow)
    if n:
        state._one_body = False
    if n and not grow:
        state.pose[dst] = state.pose[src]
        state.pose_m[dst] = state.pose_m[src]
        alive[dst] = 1
    return int(dst), int(n)


@njit(cache=True, nogil=True)
def _members(keys, vals, body, density, ijk, src, keep):
    n = 0
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        ok = False
        if b >= 0:
            off = voxel_offset(i, j, k)
            ok = body[b, off] == src and density[b, off] > 0.0
        keep[q] = ok
        n += ok
    return n


def publish_split(state, src: int, ijk, t_s: float, dst: int | None = None,
                  ordered: bool = False) -> tuple[int, int]:
    """:func:`split_body` on a live state, published as ``SPLIT`` tissue events.

    One record per voxel that moved (``body`` the new body, ``ijk`` the
    voxel, ``n`` the voxels moved in all, ``value[0]`` the body split), in
    one block, so that every replica moves exactly the same voxels. Voxels
    listed twice move (and are published) once. A ``dst`` that exists
    already takes the voxels (grows: a later block of a sliced split,
    :mod:`bonesim.engine.split_jobs`).

    Parameters
    ----------
    ordered : bool
        Publish in the order of ``ijk`` (first listing of each voxel);
        default: sorted in ``(i, j, k)`` order.

    Returns
    -------
    dst, n : int
        The new body (-1 when no voxel could move: nothing is published).
    """
    ijk = np.asarray(ijk, dtype=np.int32).reshape(-1, 3)
    if ordered:
        _, first = np.unique(ijk, axis=0, return_index=True)
        ijk = np.ascontiguousarray(ijk[np.sort(first)])
    else:
        ijk = np.unique(ijk, axis=0)
    g = state.grid
    keep = np.zeros(len(ijk), np.bool_)
    if not 0 <= src < len(state.alive) or not state.alive[src]:
        raise ValueError(f"split: body {src} does not exist")
    n = _members(g.keys, g.vals, state.body, g.density, ijk, np.uint8(src), keep)
    if n == 0:
        return -1, 0
    moved = ijk[keep]
    grow = dst is not None and 0 <= dst < len(state.alive) and bool(state.alive[dst])
    dst, n = split_body(state, src, moved, dst, grow=grow)
    state.tissue.append(kind=np.full(n, SPLIT, np.uint8), body=np.full(n, dst, np.uint8),
                        label=np.zeros(n, np.uint8), t_s=np.full(n, float(t_s)),
                        ijk=moved, n=np.full(n, n, np.int32),
                        value=np.pad(np.full((n, 1), float(src)), ((0, 0), (0, 6))))
    return dst, n


@njit(cache=True, nogil=True)
def _split_box(keys, vals, body, density, lo, hi, src, dst, t, bounds,
               ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head):
    # pass 0 counts (every record carries the total), pass 1 moves and publishes
    n = 0
    for p in range(2):
        m = 0
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for k in range(lo[2], hi[2] + 1):
                    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                                   k >> BRICK_SHIFT)
                    if b < 0:
                        continue
                    off = voxel_offset(i, j, k)
                    if body[b, off] != src or density[b, off] <= 0.0:
                        continue
                    if p == 1:
                        body[b, off] = dst
                        if m == 0:
                            bounds[dst, 0], bounds[dst, 1], bounds[dst, 2] = i, j, k
                            bounds[dst, 3], bounds[dst, 4], bounds[dst, 5] = i, j, k
                        bounds[dst, 0] = min(bounds[dst, 0], i)
                        bounds[dst, 1] = min(bounds[dst, 1], j)
                        bounds[dst, 2] = min(bounds[dst, 2], k)
                        bounds[dst, 3] = max(bounds[dst, 3], i)
                        bounds[dst, 4] = max(bounds[dst, 4], j)
                        bounds[dst, 5] = max(bounds[dst, 5], k)
                        push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                    ev_head, SPLIT, dst, 0, t, i, j, k, n, float(src), 0.0,
                                    0.0)
                    m += 1
        n = m
        if n == 0:
            break
    return n


def publish_split_box(state, src: int, lo, hi, t_s: float) -> tuple[int, int]:
    """:func:`publish_split` of the voxels of body ``src`` in the box ``lo ..
    hi`` (voxel indices in its frame, inclusive), walking the box in place:
    no voxel list is built (the haptic loop runs it between two steps). The
    records are the same, in the same (sorted) order, as :func:`publish_split`
    of the box's voxels gives.

    Returns
    -------
    dst, n : int
        The new body (-1 when no voxel could move: nothing is published).
    """
    alive = state.alive
    if not 0 <= src < len(alive) or not alive[src]:
        raise ValueError(f"split: body {src} does not exist")
    free = np.flatnonzero(alive == 0)
    if len(free) == 0:
        raise ValueError(f"split: all {len(alive)} bodies are in use (max_bodies)")
    dst = int(free[0])
    g = state.grid
    lo = np.maximum(np.asarray(lo, np.int64), 0)
    hi = np.minimum(np.asarray(hi, np.int64), np.asarray(g.shape, np.int64) - 1)
    ev = state.tissue.fields
    n = _split_box(g.keys, g.vals, state.body, g.density, lo, hi, np.uint8(src),
                   np.uint8(dst), float(t_s), state.bounds, ev["kind"], ev["body"],
                   ev["label"], ev["t_s"], ev["ijk"], ev["n"], ev["value"], state.tissue.head)
    if n == 0:
        return -1, 0
    state.pose[dst] = state.pose[src]
    state.pose_m[dst] = state.pose_m[src]
    alive[dst] = 1
    state._one_body = False
    return dst, int(n)


def publish_pose(state, body: int, pose, t_s: float) -> None:
    """:func:`set_pose` on a live state, published as a ``POSE`` tissue event."""
    set_pose(state, body, pose)
    push_event(state.tissue, POSE, float(t_s), body=body, value=state.pose[body])


def set_pose(state, body: int, pose) -> None:
    """Place body ``body`` at ``pose`` (body-to-case transform), in place."""
    if not 0 <= body < len(state.alive) or not state.alive[body]:
        raise ValueError(f"pose: body {body} does not exist")
    p = validate_pose(pose)
    state._one_body = False
    state.pose[body] = p
    state.pose_m[body] = pose_matrix(p)


def body_voxel_counts(state) -> np.ndarray:
    """Voxels holding material per body id, (max_bodies,) int64."""
    held = state.grid.density > 0.0
    return np.bincount(state.body[held], minlength=len(state.alive))[:len(state.alive)]


def to_body_frame(pose_m, pts_mm) -> np.ndarray:
    """Points of the case frame in a body's own frame, ``R^T (p - t)``.

    Parameters
    ----------
    pose_m : (3, 4) float64
        The body's ``[R | t]`` (``state.pose_m[b]``).
    pts_mm : (3,) or (n, 3) float
        Points, case frame [mm].

    Returns
    -------
    float64 array of the shape of ``pts_mm``, body frame [mm].
    """
    m = np.asarray(pose_m, dtype=np.float64)
    p = np.asarray(pts_mm, dtype=np.float64)
    return (p - m[:, 3]) @ m[:, :3]


def to_case_frame(pose_m, pts_mm) -> np.ndarray:
    """Points of a body's own frame in the case frame, ``R p + t``.

    Parameters
    ----------
    pose_m : (3, 4) float64
        The body's ``[R | t]``.
    pts_mm : (3,) or (n, 3) float
        Points, body frame [mm].

    Returns
    -------
    float64 array of the shape of ``pts_mm``, case frame [mm].
    """
    m = np.asarray(pose_m, dtype=np.float64)
    p = np.asarray(pts_mm, dtype=np.float64)
    return p @ m[:, :3].T + m[:, 3]


def posed_bodies(state) -> np.ndarray:
    """Ids of the living bodies whose pose is not exactly the identity, (n,) int64."""
    alive = np.flatnonzero(state.alive)
    return np.array([b for b in alive if not is_identity(state.pose[b])], dtype=np.int64)


class Bodies(NamedTuple):
    """The body arrays of a state, for consumers that need nothing else.

    ``body`` (n_bricks, 512) uint8, ``pose`` (max_bodies, 7), ``pose_m``
    (max_bodies, 3, 4), ``alive`` (max_bodies,) uint8, ``bounds``
    (max_bodies, 6) int32, as in the module docstring. A
    :class:`~bonesim.engine.model.State` has the same attributes, so either
    may be passed where a consumer takes ``bodies``.
    """

    body: np.ndarray
    pose: np.ndarray
    pose_m: np.ndarray
    alive: np.ndarray
    bounds: np.ndarray

    @classmethod
    def of(cls, src) -> "Bodies":
        """The body arrays of a State, a replica's state, or a dict of arrays
        named as in :func:`body_arrays_spec` (e.g. shared memory)."""
        if isinstance(src, dict):
            return cls(*(src[name] for name in cls._fields))
        return cls(*(getattr(src, name) for name in cls._fields))


@njit(cache=True, nogil=True)
def _all_identity(alive, pose):
    for b in range(alive.shape[0]):
        if alive[b] != 0 and not (pose[b, 0] == 0.0 and pose[b, 1] == 0.0
                                  and pose[b, 2] == 0.0 and pose[b, 3] == 1.0
                                  and pose[b, 4] == 0.0 and pose[b, 5] == 0.0
                                  and pose[b, 6] == 0.0):
            return False
    return True


def all_identity(bodies) -> bool:
    """True when every living body sits exactly at the identity pose (then
    every voxel's grid position is its case-frame position: a consumer may
    ignore bodies). ``bodies``: anything with ``alive`` and ``pose``; None
    counts as one body at the identity."""
    if bodies is None:
        return True
    return bool(_all_identity(bodies.alive, bodies.pose))


@njit(cache=True, nogil=True)
def _pose_groups(alive, pose, out):
    for b in range(alive.shape[0]):
        out[b] = -1
        if alive[b] == 0:
            continue
        out[b] = b
        for a in range(b):
            if out[a] == a:
                same = True
                for c in range(7):
                    if pose[a, c] != pose[b, c]:
                        same = False
                if same:
                    out[b] = a
                    break


def pose_groups(bodies, out=None) -> np.ndarray:
    """For every body, the lowest living body id at exactly the same pose.

    Bodies at the same pose lie in one frame: their voxels may be read
    together (as :func:`plan_passes` groups them for the haptic step).

    Parameters
    ----------
    bodies : Bodies or State
        ``alive`` and ``pose`` are read.
    out : (max_bodies,) int32, optional
        Written in place and returned.

    Returns
    -------
    (max_bodies,) int32
        Group id (a body id) per body; -1 for bodies that do not exist.
    """
    if out is None:
        out = np.empty(len(bodies.alive), np.int32)
    _pose_groups(bodies.alive, bodies.pose, out)
    return out


@njit(cache=True, nogil=True)
def _voxel_bodies(keys, vals, body, ijk, none, out):
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        out[q] = body[b, voxel_offset(i, j, k)] if b >= 0 else none


def voxel_bodies(grid, body, ijk, none: int = 0) -> np.ndarray:
    """The body of each voxel.

    A removed voxel keeps its body id, so this names the body a removal came
    from.

    Parameters
    ----------
    grid : Grid
        Its brick table is read.
    body : (n_bricks, 512) uint8
        Body id per voxel (a state's ``body``).
    ijk : (n, 3) int
        Voxels, grid coordinates.
    none : int
        The id given to voxels outside the grid's bricks (default 0, the
        main body; :data:`BODY_LIMIT` to tell them apart).

    Returns
    -------
    (n,) int32
    """
    ijk = np.ascontiguousarray(np.asarray(ijk, dtype=np.int64).reshape(-1, 3))
    out = np.zeros(len(ijk), np.int32)
    _voxel_bodies(grid.keys, grid.vals, body, ijk, int(none), out)
    return out


def majority_bodies(bodies, voxel_sets, density=None, out=None) -> np.ndarray:
    """The body holding most of each set of voxels (e.g. a structure's).

    Parameters
    ----------
    bodies : Bodies or State
        ``body`` and ``alive`` are read.
    voxel_sets : list of (bricks, offsets)
        Each set as index arrays into ``body`` (``np.nonzero`` of a mask
        laid out like the grid).
    density : (n_bricks, 512) float32, optional
        Only voxels with density > 0 vote (default: all).
    out : (k,) int64, optional
        The previous answer, updated in place: a set with no voter keeps
        its body. Default: zeros (body 0).

    Returns
    -------
    (k,) int64
        Ties go to the lowest body id.
    """
    out = np.zeros(len(voxel_sets), np.int64) if out is None else out
    living = np.flatnonzero(bodies.alive)
    if len(living) == 1:                         # one body holds everything
        out[:] = living[0]
        return out
    for q, (bb, oo) in enumerate(voxel_sets):
        ids = bodies.body[bb, oo]
        if density is not None:
            ids = ids[density[bb, oo] > 0.0]
        if len(ids):
            out[q] = int(np.argmax(np.bincount(ids, minlength=len(bodies.alive))))
    return out
