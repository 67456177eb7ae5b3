"""Was a voxel visible when it was removed?

SPEC (voxel visibility): when a voxel is removed, trace the segment from it to
the eye; if the segment passes through any bone voxel other than those in
contact with the drill, the removal was not visible (the trainee was
undercutting).

:func:`hidden_by` walks the segment voxel by voxel (Amanatides & Woo's 3D
DDA) through the hashed grid, so each query costs a few microseconds.
:class:`VisibilityTracker` keeps a replica of the tissue that removals are
applied to in order, so each removal is judged against the bone as it was at
that moment. The recorder uses it to fill the ``visible`` column of a
session's removals.

Bodies (:mod:`bonesim.engine.bodies`): each removal is judged in its own
body's frame. The eye and the burr centre are transformed into that frame
(``R^T (p - t)`` with the body's pose at judging time) and the segment is
marched through the voxels of the bodies at exactly the same pose as that
body (one pose group, see :func:`~bonesim.engine.bodies.pose_groups`). Bodies
at other poses do **not** occlude: a fragment that was moved is not looked
through, and one moved into the line of sight does not hide a removal. While
every body sits at the identity pose the bodies are ignored and the judge is
exactly the one-grid judge.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine import events
from bonesim.engine.bodies import all_identity, pose_groups, to_body_frame
from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.kernel_args import filled
from bonesim.engine.replica import TissueReplica

__all__ = ["CONTACT_MARGIN_VOXELS", "occluders", "judge_removals", "VisibilityTracker"]

#: Voxels whose centre lies within the burr radius plus this many voxel
#: edges of the burr centre count as "in contact with the drill".
CONTACT_MARGIN_VOXELS = 1.0


@njit(cache=True, nogil=True)
def _hidden(keys, vals, density, label, occluder, body, group, gsel, origin, spacing,
            shape, i0, j0, k0, eye, tool, contact_r2):
    """1 if an occluding voxel (other than the start voxel and voxels near
    the tool) lies on the segment from voxel (i0, j0, k0)'s centre to ``eye``;
    with ``gsel >= 0`` only voxels whose body is in group ``gsel`` occlude."""
    # voxel coordinates in which voxel i spans [i, i + 1)
    p = np.empty(3)
    d = np.empty(3)
    p[0], p[1], p[2] = i0 + 0.5, j0 + 0.5, k0 + 0.5
    for a in range(3):
        d[a] = (eye[a] - origin[a]) / spacing + 0.5 - p[a]
    cell = np.array([i0, j0, k0], dtype=np.int64)
    step = np.zeros(3, dtype=np.int64)
    t_max = np.full(3, np.inf)
    t_delta = np.full(3, np.inf)
    for a in range(3):
        if d[a] > 0.0:
            step[a] = 1
            t_max[a] = (cell[a] + 1 - p[a]) / d[a]
            t_delta[a] = 1.0 / d[a]
        elif d[a] < 0.0:
            step[a] = -1
            t_max[a] = (cell[a] - p[a]) / d[a]
            t_delta[a] = -1.0 / d[a]
    while True:
        a = 0
        if t_max[1] < t_max[a]:
            a = 1
        if t_max[2] < t_max[a]:
            a = 2
        if t_max[a] > 1.0:
            return 0                      # reached the eye's voxel
        cell[a] += step[a]
        t_max[a] += t_delta[a]
        if cell[a] < 0 or cell[a] >= shape[a]:
            return 0                      # left the grid: nothing beyond
        i, j, k = cell[0], cell[1], cell[2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b < 0:
            continue
        o = voxel_offset(i, j, k)
        if density[b, o] <= 0.0 or occluder[label[b, o]] == 0:
            continue
        if gsel >= 0 and group[body[b, o]] != gsel:
            continue                      # a body at another pose
        dx = origin[0] + spacing * i - tool[0]
        dy = origin[1] + spacing * j - tool[1]
        dz = origin[2] + spacing * k - tool[2]
        if dx * dx + dy * dy + dz * dz <= contact_r2:
            continue                      # touched by the burr: not an occluder
        return 1


@njit(cache=True, nogil=True)
def _remove_and_judge(keys, vals, density, label, occluder, body, group, gsel, origin,
                      spacing, shape, ijk, eye, tool, contact_r, out):
    """For each removal in order: judge it (in the frame of pose group
    ``gsel[q]``, -1: every voxel), then remove the voxel."""
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        r2 = contact_r[q] * contact_r[q]
        out[q] = 1 - _hidden(keys, vals, density, label, occluder, body, group, gsel[q],
                             origin, spacing, shape, i, j, k, eye[q], tool[q], r2)
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b >= 0:
            density[b, voxel_offset(i, j, k)] = 0.0


def occluders(structures) -> np.ndarray:
    """(n_labels + 1,) uint8: 1 for labels whose structure kind is bone."""
    out = np.zeros(len(structures) + 1, np.uint8)
    for s, st in enumerate(structures, start=1):
        out[s] = 1 if st.kind == "bone" else 0
    return out


def judge_removals(grid, occluder, ijk, eye_mm, tool_mm, contact_r_mm, body=None,
                   bodies=None) -> np.ndarray:
    """Judge removals in order against ``grid``, removing each voxel after.

    Parameters
    ----------
    grid : Grid
        Tissue just before the first removal; its density is changed in place.
    occluder : (n_labels + 1,) uint8
        Labels that block the view (:func:`occluders`).
    ijk : (n, 3) int
        Removed voxels, in the order they were removed, each in its body's
        frame.
    eye_mm, tool_mm : (n, 3) float
        Eye position and burr centre at each removal [mm], case frame.
    contact_r_mm : (n,) float
        Contact radius around the burr centre [mm] (burr radius plus
        :data:`CONTACT_MARGIN_VOXELS` voxels).
    body : (n,) int, optional
        The body of each removal (the events' ``body`` column).
    bodies : Bodies or State, optional
        The body arrays (``body`` laid out like ``grid.density``, ``pose``,
        ``pose_m``, ``alive``): each removal is judged in its body's frame,
        against the bodies at its body's pose only (module docstring). None,
        or every body at the identity: against every voxel.

    Returns
    -------
    visible : (n,) int8
        1 visible, 0 hidden.
    """
    ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
    n = len(ijk)
    eye = filled(eye_mm, (n, 3), np.float64)
    tool = filled(tool_mm, (n, 3), np.float64)
    r = filled(contact_r_mm, (n,), np.float64)
    if not (np.isfinite(eye).all() and np.isfinite(tool).all()):
        raise ValueError("eye and tool positions must be finite")
    occ = np.ascontiguousarray(occluder, dtype=np.uint8)
    if len(occ) <= int(grid.label.max(initial=0)):
        raise ValueError(f"occluder table has {len(occ)} entries; the grid uses label "
                         f"{int(grid.label.max())}")
    out = np.empty(n, np.int8)
    if body is None or all_identity(bodies):
        vbody, group, gsel = _NO_BODY, _NO_GROUP, np.full(n, -1, np.int32)
    else:
        vbody, group, gsel, eye, tool = _in_body_frames(grid, body, bodies, eye, tool)
    _remove_and_judge(grid.keys, grid.vals, grid.density, grid.label, occ, vbody, group,
                      gsel, np.asarray(grid.origin_mm, np.float64), float(grid.spacing_mm),
                      np.asarray(grid.shape, np.int64), ijk, eye, tool, r, out)
    return out


# body arrays of the judge that ignores bodies (never read)
_NO_BODY = np.zeros((1, 512), np.uint8)
_NO_GROUP = np.zeros(1, np.int32)


def _in_body_frames(grid, body, bodies, eye, tool):
    """Pose group of each removal's body and its eye and burr centre in that
    body's frame [mm]."""
    n = len(eye)
    body = np.broadcast_to(np.asarray(body, np.int64), (n,))
    if n and (body.min() < 0 or body.max() >= len(bodies.alive)
              or not bodies.alive[body].all()):
        raise ValueError("a removal names a body that does not exist")
    if bodies.body.shape != grid.density.shape:
        raise ValueError(f"bodies.body has shape {bodies.body.shape}, the grid's density "
                         f"{grid.density.shape}")
    group = pose_groups(bodies)
    eye, tool = eye.copy(), tool.copy()
    for b in np.unique(body):
        sel = body == b
        eye[sel] = to_body_frame(bodies.pose_m[b], eye[sel])
        tool[sel] = to_body_frame(bodies.pose_m[b], tool[sel])
    return (bodies.body, group, np.ascontiguousarray(group[body], dtype=np.int32),
            eye, tool)


class VisibilityTracker:
    """Judges a run's removals as they come, against a replica of the tissue.

    Parameters
    ----------
    models : list of Model
        One per burr index (for the contact radius); ``models[0].grid`` is the
        initial tissue.
    eye_mm : (3,) float
        Eye used until a camera pose is known (the case camera) [mm].
    """

    def __init__(self, models, eye_mm):
        self.models = models
        #: The tissue as the removals judged so far left it (removals are
        #: applied by the judge itself, in order; resets, splits and poses
        #: through the replica).
        self.replica = TissueReplica(models[0])
        self.initial = models[0].grid
        self.occluder = occluders(models[0].structures)
        margin = CONTACT_MARGIN_VOXELS * self.initial.spacing_mm
        self.contact_r = np.array([m.burr.radius_mm + margin for m in models])
        self.eye = np.asarray(eye_mm, float).copy()
        # the last sample seen and the camera poses not yet passed
        self._s_t = np.zeros(0)
        self._s_pos = np.zeros((0, 3))
        self._s_burr = np.zeros(0, np.int64)
        self._cam_t = np.zeros(0)
        self._cam_eye = np.zeros((0, 3))

    def warm(self) -> None:
        """Load the kernels into this process now: numba's first call in a
        process also sets up its compiler target (about a second of imports,
        more under load), and a recorder's writer must not spend that at the
        run's first removal with its flushes held up. Judges no removal."""
        n = np.zeros((0, 3))
        judge_removals(self.replica.grid, self.occluder, np.zeros((0, 3), np.int64), n, n,
                       np.zeros(0))

    def add_samples(self, s: dict) -> None:
        """Samples drained since the last call (``t_s``, ``pos_mm``, ``burr``)."""
        if len(s["t_s"]) == 0:
            return
        keep = slice(-1, None)              # the previous batch's last row
        self._s_t = np.concatenate([self._s_t[keep], s["t_s"]])
        self._s_pos = np.concatenate([self._s_pos[keep], s["pos_mm"]])
        self._s_burr = np.concatenate([self._s_burr[keep], s["burr"].astype(np.int64)])

    def add_camera(self, c: dict) -> None:
        """Camera poses drained since the last call (``t_s``, ``eye_mm``)."""
        if len(c["t_s"]):
            self._cam_t = np.concatenate([self._cam_t, c["t_s"]])
            self._cam_eye = np.concatenate([self._cam_eye, c["eye_mm"]])

    def judge(self, ev: dict) -> np.ndarray:
        """``visible`` (n,) int8 for tissue events drained since the last call
        (1 visible, 0 hidden for removals; -1 for other kinds); the samples of
        their steps must have been added already. The events are applied to
        the tracker's replica in order (resets, splits, poses), removals as
        they are judged."""
        kinds = np.asarray(ev["kind"])
        n = len(kinds)
        vis = np.full(n, -1, np.int8)
        if n == 0:
            return vis
        rem = kinds == events.REMOVED
        if rem.any():
            t_last = ev["t_s"][np.flatnonzero(rem)[-1]]
            if len(self._s_t) == 0 or t_last > self._s_t[-1]:
                raise ValueError("removals must come after the samples of their steps")
        starts = np.concatenate(([0], np.flatnonzero(np.diff(kinds)) + 1, [n]))
        for a, b in zip(starts[:-1], starts[1:]):
            part = {f: c[a:b] for f, c in ev.items()}
            if kinds[a] == events.REMOVED:
                vis[a:b] = self._judge_run(part)
            else:
                self.replica.apply(part)
        return vis

    def _judge_run(self, rem: dict) -> np.ndarray:
        idx = np.clip(np.searchsorted(self._s_t, rem["t_s"]), 0, len(self._s_t) - 1)
        # the eye: the last camera pose at or before each removal
        c = np.searchsorted(self._cam_t, rem["t_s"], side="right") - 1
        eyes = np.where((c >= 0)[:, None], self._cam_eye[np.maximum(c, 0)]
                        if len(self._cam_t) else self.eye, self.eye)
        if c[-1] >= 0:                       # poses before that one are passed
            self.eye = self._cam_eye[c[-1]].copy()
            self._cam_t, self._cam_eye = self._cam_t[c[-1]:], self._cam_eye[c[-1]:]
        return judge_removals(self.replica.grid, self.occluder, rem["ijk"], eyes,
                              self._s_pos[idx], self.contact_r[self._s_burr[idx]],
                              rem["body"], self.replica.state)
