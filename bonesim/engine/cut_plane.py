"""The cut plane: a posed rectangle that removes every voxel its rays pass.

A tool with no force feedback and infinite power (SPEC "Other tools"; the
reference simulator's plane tool). A **stroke** is a rectangle posed in
6-DOF with a depth:

``pose`` (7,) float64
    ``(cx, cy, cz [mm], qw, qx, qy, qz)``: the rectangle's centre in the case
    frame and the unit quaternion of its rotation ``R`` (plane to case
    frame). Its in-plane axes are ``u = R e_x`` (width) and ``v = R e_y``
    (height), its normal ``n = R e_z``: the rays go along ``+n``, into the
    bone.
``width_mm, height_mm, depth_mm`` [mm]
    The rectangle's extent along ``u`` and ``v``, and how far each ray goes.
    They are rounded to whole micrometres (:data:`SIZE_QUANTUM_MM`), so the
    ``CUT`` record that carries them (below) reproduces the stroke exactly.

The rectangle is discretised into samples :data:`SAMPLES_PER_VOXEL` to a voxel
edge ``h`` along each in-plane axis: ``n_u = ceil(width * SAMPLES_PER_VOXEL /
h)`` columns at ``-width/2 + (a + 1/2) width / n_u`` (a = 0 .. n_u - 1), and
likewise rows along ``v``. From each sample a ray of length ``depth`` goes
along ``n``; every voxel the ray passes through (a segment of positive length
inside the voxel's cube) loses all its density. The traversal is exact
(Amanatides and Woo's voxel walk, with every boundary crossing computed
directly from the ray's start, not accumulated).

Two samples per voxel edge: the projection of a voxel's cube on the plane
contains a disc of radius ``h / 2``, larger than the covering radius ``h /
(2 sqrt 2)`` of a square lattice of spacing ``h / 2``, so every voxel whose
projection lies inside the rectangle and whose depth range the rays cover
is removed: a stroke leaves no voxel bridge behind (the fragment finder's
26-connectivity would see one).

Bodies
------
Each living body is cut in its own frame: the rectangle is carried into the
body's frame by its pose (``R_b^T (p - t_b)``) and the rays walk the body's
voxel box (:mod:`bonesim.engine.bodies`); only the body's own voxels are
removed. Bodies are visited in id order, samples row by row, voxels in ray
order, so a stroke is deterministic.

Events
------
Published on the tissue-event stream (:mod:`bonesim.engine.events`) at the
time ``t_s`` of the step the stroke precedes: one ``REMOVED`` record per voxel
(so the dust, the surfaces, the replica, the recorder and the metrics follow
as for drilling), one ``INJURY`` record per body and injury-emitting
structure that lost voxels (``n`` the count, ``value`` the rectangle's
centre), then one ``CUT`` record that describes the stroke: ``ijk`` the
width, height and depth in micrometres, ``n`` the voxels removed, ``value``
the pose. Replay re-applies a stroke from its ``CUT`` record
(:func:`publish_cut_record`).

Strokes in slices
-----------------
A stroke whose rays would walk more voxels than a world step may (the
``[cut_plane] voxels_per_step`` of ``bonesim/data/slicing.toml``:
:func:`rays_per_step` whole rays a step), or any stroke while one is under way,
is done in slices (:func:`queue_cut`, :func:`advance_cuts`): its ``CUT``
record comes first, at the command's step, with ``n`` = minus the rays per
step (a stroke done at once has ``n`` >= 0, its voxels removed), and every
following world step walks that many more rays, in the same order as at
once (bodies by id, samples row by row), publishing that step's removals at
its time; a body's ``INJURY`` records follow its last ray. The slicing is a
fixed number of rays, so replay, reading ``n``, repeats it step for step.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.bodies import validate_pose
from bonesim.engine.events import CUT as _EV_CUT
from bonesim.engine.events import INJURY as _EV_INJURY
from bonesim.engine.events import REMOVED as _EV_REMOVED
from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.haptics import push_event_kernel

__all__ = ["SAMPLES_PER_VOXEL", "SIZE_QUANTUM_MM", "MAX_SIZE_MM", "plane_pose",
           "plane_axes", "quantize_size", "sample_offsets", "cut_plane", "publish_cut",
           "publish_cut_record", "rays_per_step", "stroke_rays", "CutJob", "queue_cut",
           "advance_cuts"]

#: Ray samples per voxel edge along each in-plane axis (see the module docstring).
SAMPLES_PER_VOXEL = 2
#: Stroke sizes are whole multiples of this [mm] (1 um).
SIZE_QUANTUM_MM = 1e-3
#: Largest width, height or depth of a stroke [mm] (the record holds int32 um).
MAX_SIZE_MM = 1000.0


def plane_axes(pose) -> np.ndarray:
    """The rectangle's axes ``u, v, n`` (rows of a (3, 3) array, case frame)
    of a stroke pose ``(cx, cy, cz, qw, qx, qy, qz)``."""
    _, _, _, w, x, y, z = (float(c) for c in pose)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return np.ascontiguousarray(R.T)


def plane_pose(centre_mm, normal, u_axis=None) -> np.ndarray:
    """A stroke pose from the rectangle's centre, its normal (the cut's
    direction, into the bone) and optionally its width axis.

    Parameters
    ----------
    centre_mm : (3,) float
        Centre of the rectangle, case frame [mm].
    normal : (3,) float
        Direction the rays go (any non-zero length).
    u_axis : (3,) float, optional
        Width direction; its part along ``normal`` is dropped. Default: the
        case axis least aligned with the normal, made perpendicular.

    Returns
    -------
    (7,) float64
        ``(cx, cy, cz, qw, qx, qy, qz)``.
    """
    c = np.asarray(centre_mm, np.float64).reshape(-1)
    n = np.asarray(normal, np.float64).reshape(-1)
    if c.shape != (3,) or n.shape != (3,) or not (np.isfinite(c).all() and np.isfinite(n).all()):
        raise ValueError(f"cut plane: centre {centre_mm!r} and normal {normal!r} must be 3 "
                         "finite numbers each")
    nn = float(np.linalg.norm(n))
    if not nn > 0:
        raise ValueError("cut plane: the normal is zero")
    n = n / nn
    u = np.eye(3)[int(np.argmin(np.abs(n)))] if u_axis is None else \
        np.asarray(u_axis, np.float64).reshape(3)
    u = u - (u @ n) * n
    un = float(np.linalg.norm(u))
    if not un > 1e-9:
        raise ValueError(f"cut plane: the width axis {u_axis!r} is parallel to the normal")
    u = u / un
    v = np.cross(n, u)
    R = np.column_stack([u, v, n])
    # rotation matrix -> unit quaternion (Shepperd)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return np.concatenate([c, q])


def quantize_size(width_mm, height_mm, depth_mm) -> np.ndarray:
    """The sizes as whole micrometres, (3,) int64, or ValueError naming the
    bad one (each must be finite and in ``[0, MAX_SIZE_MM]``)."""
    out = np.zeros(3, np.int64)
    for q, (name, v) in enumerate((("width_mm", width_mm), ("height_mm", height_mm),
                                   ("depth_mm", depth_mm))):
        v = float(v)
        if not (math.isfinite(v) and 0.0 <= v <= MAX_SIZE_MM):
            raise ValueError(f"cut plane: {name} must lie in [0, {MAX_SIZE_MM}] mm, got {v}")
        out[q] = int(round(v / SIZE_QUANTUM_MM))
    return out


def sample_offsets(size_mm: float, spacing_mm: float) -> np.ndarray:
    """In-plane offsets of the samples along one axis of a rectangle of
    extent ``size_mm`` [mm] (see the module docstring), (n,) float64 [mm]."""
    n = max(1, int(math.ceil(size_mm * SAMPLES_PER_VOXEL / spacing_mm - 1e-9)))
    step = size_mm / n
    return -0.5 * size_mm + (np.arange(n) + 0.5) * step


@njit(cache=True, nogil=True)
def _walk(keys, vals, density, label, body, b, y0, dy, length, lo, hi, t, removed_by_label,
          lost, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head):
    """Walk one ray (index frame shifted by 1/2: voxel i spans [i, i + 1))
    through the box ``lo .. hi`` (inclusive voxel indices), removing body
    ``b``'s voxels. Returns the voxels removed."""
    # clip [0, length] to the box
    t0 = 0.0
    t1 = length
    for a in range(3):
        if dy[a] == 0.0:
            if y0[a] < lo[a] or y0[a] >= hi[a] + 1:
                return 0
        else:
            ta = (lo[a] - y0[a]) / dy[a]
            tb = (hi[a] + 1 - y0[a]) / dy[a]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if not t1 > t0:
        return 0
    i0 = 0
    i1 = 0
    i2 = 0
    for a in range(3):
        c = int(math.floor(y0[a] + t0 * dy[a]))
        if c < lo[a]:
            c = lo[a]
        if c > hi[a]:
            c = hi[a]
        # a start on a boundary: the voxel the ray is in just after t0
        if dy[a] < 0.0 and c > lo[a] and (c - y0[a]) / dy[a] <= t0:
            c -= 1
        elif dy[a] > 0.0 and c < hi[a] and (c + 1 - y0[a]) / dy[a] <= t0:
            c += 1
        if a == 0:
            i0 = c
        elif a == 1:
            i1 = c
        else:
            i2 = c
    n = 0
    tc = t0
    while True:
        # next boundary crossing of each axis, from the ray's start
        tn = t1
        ax = -1
        for a in range(3):
            ia = i0 if a == 0 else (i1 if a == 1 else i2)
            if dy[a] > 0.0:
                ta = (ia + 1 - y0[a]) / dy[a]
            elif dy[a] < 0.0:
                ta = (ia - y0[a]) / dy[a]
            else:
                continue
            if ta < tn:
                tn = ta
                ax = a
        if tn > tc:
            bk = find_brick(keys, vals, i0 >> BRICK_SHIFT, i1 >> BRICK_SHIFT, i2 >> BRICK_SHIFT)
            if bk >= 0:
                off = voxel_offset(i0, i1, i2)
                if density[bk, off] > 0.0 and body[bk, off] == b:
                    density[bk, off] = 0.0
                    lab = label[bk, off]
                    removed_by_label[lab] += 1
                    lost[b, lab] += 1
                    push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                ev_head, _EV_REMOVED, b, lab, t, i0, i1, i2, 0, 0.0, 0.0, 0.0)
                    n += 1
            tc = tn
        if ax < 0 or tc >= t1:
            break
        if ax == 0:
            i0 += 1 if dy[0] > 0.0 else -1
            if i0 < lo[0] or i0 > hi[0]:
                break
        elif ax == 1:
            i1 += 1 if dy[1] > 0.0 else -1
            if i1 < lo[1] or i1 > hi[1]:
                break
        else:
            i2 += 1 if dy[2] > 0.0 else -1
            if i2 < lo[2] or i2 > hi[2]:
                break
    return n


@njit(cache=True, nogil=True)
def _cut_slice(keys, vals, density, label, body, alive, pose_m, bounds, shape, origin,
               spacing, centre, axes, su, sv, depth, t, injury, removed_by_label, lost,
               cursor, budget, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
               ev_head):
    # rays from cursor (body, ray = p * len(sv) + q) on, at most ``budget`` of
    # them; a body's INJURY records follow its last ray
    y0 = np.empty(3)
    dy = np.empty(3)
    cb = np.empty(3)
    ub = np.empty(3)
    vb = np.empty(3)
    nb = np.empty(3)
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    nv = sv.shape[0]
    n_rays = su.shape[0] * nv
    total = 0
    done = 0
    b = cursor[0]
    r = cursor[1]
    while b < alive.shape[0] and done < budget:
        if alive[b] == 0:
            b += 1
            r = 0
            continue
        if r == 0:
            for lab in range(lost.shape[1]):
                lost[b, lab] = 0
        # the rectangle in the body's frame: R^T (p - t), axes R^T a
        for a in range(3):
            s = 0.0
            for k in range(3):
                s += pose_m[b, k, a] * (centre[k] - pose_m[b, k, 3])
            cb[a] = s
            su_ = 0.0
            sv_ = 0.0
            sn_ = 0.0
            for k in range(3):
                su_ += pose_m[b, k, a] * axes[0, k]
                sv_ += pose_m[b, k, a] * axes[1, k]
                sn_ += pose_m[b, k, a] * axes[2, k]
            ub[a] = su_
            vb[a] = sv_
            nb[a] = sn_
            lo[a] = max(bounds[b, a], 0)
            hi[a] = min(bounds[b, 3 + a], shape[a] - 1)
            dy[a] = nb[a] / spacing
        if lo[0] > hi[0] or lo[1] > hi[1] or lo[2] > hi[2]:
            b += 1
            r = 0
            continue
        while r < n_rays and done < budget:
            p = r // nv
            q = r - p * nv
            for a in range(3):
                y0[a] = (cb[a] + su[p] * ub[a] + sv[q] * vb[a] - origin[a]) / spacing + 0.5
            total += _walk(keys, vals, density, label, body, b, y0, dy, depth, lo, hi, t,
                           removed_by_label, lost, ev_kind, ev_body, ev_label, ev_t,
                           ev_ijk, ev_n, ev_value, ev_head)
            r += 1
            done += 1
        if r == n_rays:
            for lab in range(lost.shape[1]):
                if lost[b, lab] > 0 and injury[lab] != 0:
                    push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                      ev_head, _EV_INJURY, b, lab, t, 0, 0, 0, lost[b, lab],
                                      centre[0], centre[1], centre[2])
            b += 1
            r = 0
    cursor[0] = b
    cursor[1] = r
    return total


def cut_plane(state, injury, pose, width_mm: float, height_mm: float, depth_mm: float,
              t_s: float) -> int:
    """One stroke of the cut plane on a state, published as ``REMOVED`` and
    ``INJURY`` tissue events (no ``CUT`` record: see :func:`publish_cut`).

    Parameters
    ----------
    state : State
        Its grid density, ``removed_by_label`` and tissue ring change in
        place; its body arrays are read.
    injury : (n_labels + 1,) uint8
        1 for the structures whose removal is an injury (``model.injury``).
    pose : (7,) float
        ``(cx, cy, cz [mm], qw, qx, qy, qz)``, case frame (module docstring;
        :func:`plane_pose` builds one).
    width_mm, height_mm, depth_mm : float
        Extent along ``u``, ``v`` and the rays' length along ``n`` [mm];
        used as given (:func:`publish_cut` rounds them to micrometres).
    t_s : float
        Time of the events [s].

    Returns
    -------
    int
        Voxels removed.
    """
    p = validate_pose(pose)
    for name, v in (("width_mm", width_mm), ("height_mm", height_mm), ("depth_mm", depth_mm)):
        if not (math.isfinite(float(v)) and float(v) >= 0.0):
            raise ValueError(f"cut plane: {name} must be finite and >= 0, got {v}")
    g = state.grid
    axes = plane_axes(p)
    su = sample_offsets(float(width_mm), g.spacing_mm)
    sv = sample_offsets(float(height_mm), g.spacing_mm)
    inj = np.ascontiguousarray(injury, dtype=np.uint8)
    lost = np.zeros((len(state.alive), len(inj)), np.int64)
    return _run_slice(state, inj, p, axes, su, sv, float(depth_mm), float(t_s), lost,
                      np.zeros(2, np.int64), 1 << 62)


def _run_slice(state, inj, p, axes, su, sv, depth, t_s, lost, cursor, budget) -> int:
    g = state.grid
    ev = state.tissue.fields
    return int(_cut_slice(g.keys, g.vals, g.density, g.label, state.body, state.alive,
                          state.pose_m, state.bounds, np.asarray(g.shape, np.int64),
                          g.origin_mm, float(g.spacing_mm), np.ascontiguousarray(p[:3]), axes,
                          su, sv, depth, t_s, inj, state.removed_by_label, lost, cursor,
                          int(budget), ev["kind"], ev["body"], ev["label"], ev["t_s"],
                          ev["ijk"], ev["n"], ev["value"], state.tissue.head))


def publish_cut(state, injury, pose, width_mm: float, height_mm: float, depth_mm: float,
                t_s: float) -> int:
    """A stroke (:func:`cut_plane`, sizes rounded to micrometres) followed by
    its ``CUT`` record, which lets a replay repeat it bit for bit.

    Returns
    -------
    int
        Voxels removed.
    """
    um = quantize_size(width_mm, height_mm, depth_mm)
    p = validate_pose(pose)
    w, h, d = (float(x) * SIZE_QUANTUM_MM for x in um)
    n = cut_plane(state, injury, p, w, h, d, t_s)
    state.tissue.append(kind=[_EV_CUT], body=[0], label=[0], t_s=[float(t_s)],
                        ijk=[um.astype(np.int32)], n=[n], value=[p])
    return n


def publish_cut_record(state, injury, record_ijk, record_value, t_s: float) -> int:
    """Repeat the stroke a ``CUT`` record describes (``ijk`` the sizes [um],
    ``value`` the pose), publishing it again (:func:`publish_cut`)."""
    um = np.asarray(record_ijk, np.int64)
    return publish_cut(state, injury, np.asarray(record_value, np.float64),
                       *(float(x) * SIZE_QUANTUM_MM for x in um), t_s)


def rays_per_step(depth_mm: float, spacing_mm: float) -> int:
    """Whole rays of ``depth_mm`` [mm] a world step may walk: the
    ``[cut_plane] voxels_per_step`` budget of ``bonesim/data/slicing.toml``
    over the voxels one ray can cross (``sqrt(3) depth / h + 2``), at least 1."""
    from bonesim.engine.slicing import voxels_per_step

    cells = int(math.ceil(math.sqrt(3.0) * float(depth_mm) / float(spacing_mm))) + 2
    return max(1, voxels_per_step("cut_plane") // cells)


def stroke_rays(size_um, spacing_mm: float) -> int:
    """Rays of a stroke of sizes ``size_um`` (width, height, depth [um])."""
    w, h = (float(x) * SIZE_QUANTUM_MM for x in np.asarray(size_um)[:2])
    return len(sample_offsets(w, spacing_mm)) * len(sample_offsets(h, spacing_mm))


class CutJob:
    """A stroke done in slices (:func:`queue_cut`): its rectangle, rays per
    step, per-body losses and its cursor (next body, next ray)."""

    __slots__ = ("pose", "axes", "su", "sv", "depth", "injury", "rays", "lost", "cursor")

    def __init__(self, state, injury, size_um, pose, rays: int):
        g = state.grid
        self.pose = validate_pose(pose)
        self.axes = plane_axes(self.pose)
        w, h, d = (float(x) * SIZE_QUANTUM_MM for x in np.asarray(size_um, np.int64))
        self.su = sample_offsets(w, g.spacing_mm)
        self.sv = sample_offsets(h, g.spacing_mm)
        self.depth = d
        self.injury = np.ascontiguousarray(injury, dtype=np.uint8)
        self.rays = int(rays)
        self.lost = np.zeros((len(state.alive), len(self.injury)), np.int64)
        self.cursor = np.zeros(2, np.int64)


def queue_cut(state, injury, size_um, pose, t_s: float, rays: int) -> CutJob:
    """Publish a stroke's ``CUT`` record now, with ``n = -rays`` (a stroke in
    slices of ``rays`` rays per world step; replay repeats the slicing from
    it), and queue the stroke on ``state.cut_jobs``; the world steps walk it
    (:func:`advance_cuts`), each slice's removals and a body's ``INJURY``
    records (after its last ray) at that step's time.

    Raises
    ------
    ValueError
        A bad pose or size, or ``rays`` < 1.
    """
    if int(rays) < 1:
        raise ValueError(f"cut plane: rays per step must be positive, got {rays}")
    um = np.asarray(size_um, np.int64)
    quantize_size(*(float(x) * SIZE_QUANTUM_MM for x in um))        # checks the sizes
    job = CutJob(state, injury, um, pose, rays)
    state.tissue.append(kind=[_EV_CUT], body=[0], label=[0], t_s=[float(t_s)],
                        ijk=[um.astype(np.int32)], n=[-job.rays], value=[job.pose])
    state.cut_jobs.append(job)
    return job


def advance_cuts(state, t_s: float) -> int:
    """One slice of the first queued stroke (its ``rays`` rays), at ``t_s`` [s];
    a stroke whose every body is walked leaves the queue. Returns voxels removed."""
    job = state.cut_jobs[0]
    n = _run_slice(state, job.injury, job.pose, job.axes, job.su, job.sv, job.depth,
                   float(t_s), job.lost, job.cursor, job.rays)
    if job.cursor[0] >= len(state.alive):
        state.cut_jobs.pop(0)
    return n
