"""The rigids of a run: their slots, samples and mass (:class:`RigidSet`).

The physics and the kernels are :mod:`bonesim.engine.rigid`'s (read its
docstring first); this module holds the per-slot arrays, builds a
fragment's or a plate's contact samples and mass properties (allocating:
once per rigid, never per step), and turns commands (grab, release, affix,
distract) into slot changes. :meth:`RigidSet.advance` is the per-step call.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.rigid_measure import MeasureJob, measure_budget, needs_slices
from bonesim.engine.rigid_measure import stride as _stride
from bonesim.engine.rigid import (AFFIXED, ASLEEP, BONE_DENSITY_KG_MM3, CONTACT_SHARE,
                                  DAMPING_RATIO,
                                  DEFAULT_GRAVITY_DIR, DRAG_TIME_S, DYNAMIC,
                                  FRAGMENT_STIFFNESS_N_MM_PER_KG, FREE, FRICTION_COEFF, GRAB_HZ,
                                  GRABBED,
                                  GRAVITY_MM_S2, KIND_FRAGMENT, KIND_PLATE, MAX_SAMPLES,
                                  MAX_SPEED_MM_S, N_TO_INTERNAL, SLEEP_MM, SLEEP_STEPS,
                                  SUBSTEPS, MAX_CAND, compose_poses, empty_side, pose_matrix_kernel,
                                  solid_at, tool_push_kernel,
                                  advance_kernel)

__all__ = ["RIGID_SLOTS", "body_samples", "mesh_samples", "mass_properties", "RigidSet",
           "publish_plate", "track_plates"]

#: Rigid slots of a run's state (fragments in motion and plates together).
RIGID_SLOTS = 16

# ------------------------------------------------------------------ samples
@njit(cache=True, nogil=True)
def _body_voxels(keys, vals, body, density, bid, lo, hi, ijk, surf, nrm):
    n = 0
    for i in range(lo[0], hi[0] + 1):
        for j in range(lo[1], hi[1] + 1):
            for k in range(lo[2], hi[2] + 1):
                if not solid_at(keys, vals, body, density, bid, i, j, k):
                    continue
                ijk[n, 0], ijk[n, 1], ijk[n, 2] = i, j, k
                gx, gy, gz, face = empty_side(keys, vals, body, density, bid, i, j, k)
                gn = math.sqrt(gx * gx + gy * gy + gz * gz)
                surf[n] = face and gn > 0.0
                if surf[n]:
                    nrm[n, 0], nrm[n, 1], nrm[n, 2] = gx / gn, gy / gn, gz / gn
                n += 1
    return n


def body_samples(state, b: int, max_samples: int = MAX_SAMPLES) -> dict:
    """Contact samples and mass properties of body ``b`` (a fragment).

    Samples are the centres of its surface voxels (a face neighbour is not
    the body's bone) pushed out half a voxel along the outward occupancy
    gradient, so that contact starts where the two bone surfaces meet.

    Returns
    -------
    dict
        ``smp`` (n, 3) [mm] and ``nrm`` (n, 3), body frame; ``mass_kg``,
        ``com_mm`` (3,) and ``inertia`` (3, 3) [kg mm^2] about the centre of
        mass (body frame), from every voxel of the body at
        :data:`BONE_DENSITY_KG_MM3`; ``voxels``.

    Raises
    ------
    ValueError
        ``b`` is body 0, not alive, or holds no bone.
    """
    if b == 0 or not 0 <= b < len(state.alive) or not state.alive[b]:
        raise ValueError(f"rigid: body {b} is not a fragment (a living body other than 0)")
    g = state.grid
    lo = np.asarray(state.bounds[b, :3], np.int64)
    hi = np.asarray(state.bounds[b, 3:], np.int64)
    n_box = int(np.prod(hi - lo + 1))
    ijk = np.zeros((n_box, 3), np.int64)
    surf = np.zeros(n_box, np.bool_)
    nrm = np.zeros((n_box, 3))
    n = _body_voxels(g.keys, g.vals, state.body, g.density, np.uint8(b), lo, hi, ijk, surf,
                     nrm)
    if n == 0:
        raise ValueError(f"rigid: body {b} holds no bone")
    centres = g.origin_mm + g.spacing_mm * ijk[:n].astype(np.float64)
    vox_mass = BONE_DENSITY_KG_MM3 * g.spacing_mm ** 3
    mass, com, inertia = mass_properties(centres, np.full(n, vox_mass), g.spacing_mm)
    s_idx = np.flatnonzero(surf[:n])
    s_idx = s_idx[_stride(len(s_idx), max_samples)]
    smp = centres[s_idx] + 0.5 * g.spacing_mm * nrm[s_idx]
    return {"smp": smp, "nrm": nrm[s_idx].copy(), "mass_kg": mass, "com_mm": com,
            "inertia": inertia, "voxels": n}


def mass_properties(points, masses, cell_mm: float = 0.0):
    """Mass, centre of mass and inertia tensor of point masses.

    Parameters
    ----------
    points : (n, 3) float
        Positions [mm].
    masses : (n,) float
        [kg].
    cell_mm : float
        Each point stands for a cube of this edge (adds ``m cell^2 / 6`` to
        the diagonal, which also keeps flat point sets invertible).

    Returns
    -------
    mass [kg], com (3,) [mm], inertia (3, 3) [kg mm^2] about the com.
    """
    p = np.asarray(points, np.float64)
    m = np.asarray(masses, np.float64)
    mass = float(m.sum())
    com = (p * m[:, None]).sum(axis=0) / mass
    r = p - com
    r2 = (r * r).sum(axis=1)
    inertia = np.eye(3) * float((m * r2).sum()) - (r * m[:, None]).T @ r
    inertia += np.eye(3) * mass * cell_mm ** 2 / 6.0
    return mass, com, inertia


def mesh_samples(pos, nrm, offset_mm: float, max_samples: int = MAX_SAMPLES) -> dict:
    """A mesh's contact samples: its vertices pushed out ``offset_mm`` along
    their unit normals (mesh frame), at most ``max_samples`` (evenly strided).

    Returns
    -------
    dict
        ``smp`` (n, 3) [mm], ``nrm`` (n, 3).
    """
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    nrm = np.asarray(nrm, np.float64).reshape(-1, 3)
    if pos.shape != nrm.shape or len(pos) == 0:
        raise ValueError(f"mesh samples: positions {pos.shape} and normals {nrm.shape} "
                         "must be the same non-empty (n, 3)")
    ln = np.linalg.norm(nrm, axis=1)
    if not (ln > 0).all():
        raise ValueError("mesh samples: every vertex needs a non-zero normal")
    nrm = nrm / ln[:, None]
    keep = _stride(len(pos), max_samples)
    return {"smp": pos[keep] + offset_mm * nrm[keep], "nrm": nrm[keep]}


@njit(cache=True, nogil=True)
def _sample_bodies(keys, vals, body, density, alive, pose_m, origin, spacing, pts, out):
    # the body whose solid voxel holds each point (case frame), -1 for none
    for s in range(pts.shape[0]):
        out[s] = -1
        for b in range(alive.shape[0]):
            if alive[b] == 0:
                continue
            dx = pts[s, 0] - pose_m[b, 0, 3]
            dy = pts[s, 1] - pose_m[b, 1, 3]
            dz = pts[s, 2] - pose_m[b, 2, 3]
            i = int(math.floor((pose_m[b, 0, 0] * dx + pose_m[b, 1, 0] * dy
                                + pose_m[b, 2, 0] * dz - origin[0]) / spacing + 0.5))
            j = int(math.floor((pose_m[b, 0, 1] * dx + pose_m[b, 1, 1] * dy
                                + pose_m[b, 2, 1] * dz - origin[1]) / spacing + 0.5))
            k = int(math.floor((pose_m[b, 0, 2] * dx + pose_m[b, 1, 2] * dy
                                + pose_m[b, 2, 2] * dz - origin[2]) / spacing + 0.5))
            if solid_at(keys, vals, body, density, b, i, j, k):
                out[s] = b
                break


class RigidSet:
    """The rigids of one run: fragments in motion, plates and distractors.

    Parameters
    ----------
    max_bodies : int
        The model's ``max_bodies`` (size of the per-body push table).
    capacity : int
        Slots (fragments and plates together).
    rate_hz : float
        Haptic step rate [Hz]; one :meth:`advance` is one step of
        ``1 / rate_hz`` s in :data:`SUBSTEPS` fixed substeps.
    gravity_dir : (3,) float
        Unit gravity direction, case frame (:func:`gravity_direction`).

    Attributes
    ----------
    mode : (capacity,) int8
        :data:`FREE`, :data:`ASLEEP`, :data:`DYNAMIC`, :data:`GRABBED` or
        :data:`AFFIXED` per slot.
    kind : (capacity,) int8
        :data:`KIND_FRAGMENT` or :data:`KIND_PLATE`.
    owner : (capacity,) int32
        The fragment's body id (-1 for a plate).
    host, tag : (capacity,) int32
        The body an affixed plate follows; a distractor's second body (-1).
    rpose : (capacity, 7) float64
        A plate's mesh-to-case pose (fragments: their body's pose is the state's).
    cat : (capacity,) int32
        A plate's index in the plate catalogue.
    """

    def __init__(self, max_bodies: int, capacity: int = 16, rate_hz: float = 1000.0,
                 gravity_dir=DEFAULT_GRAVITY_DIR, max_samples: int = MAX_SAMPLES):
        g = np.asarray(gravity_dir, np.float64)
        if g.shape != (3,) or not abs(float(np.linalg.norm(g)) - 1.0) < 1e-9:
            raise ValueError(f"rigid: gravity_dir must be a unit 3-vector, got {g.tolist()}")
        if not rate_hz > 0:
            raise ValueError(f"rigid: rate_hz must be positive, got {rate_hz}")
        S, M = int(capacity), int(max_samples)
        self.capacity, self.max_samples = S, M
        self.h = 1.0 / (float(rate_hz) * SUBSTEPS)
        self.gvec = g * GRAVITY_MM_S2
        self.mode = np.zeros(S, np.int8)
        self.kind = np.zeros(S, np.int8)
        self.owner = np.full(S, -1, np.int32)
        self.host = np.full(S, -1, np.int32)
        self.tag = np.full(S, -1, np.int32)
        self.cat = np.zeros(S, np.int32)
        self.rpose = np.zeros((S, 7))
        self.rel = np.zeros((S, 7))
        self.vel = np.zeros((S, 3))
        self.omg = np.zeros((S, 3))
        self.mass = np.ones(S)
        self.ib_inv = np.zeros((S, 3, 3))
        self.com_b = np.zeros((S, 3))
        self.k = np.zeros(S)
        self.c = np.zeros(S)
        self.radius = np.zeros(S)
        self.smp = np.zeros((S, M, 3))
        self.nrm = np.zeros((S, M, 3))
        self.n_smp = np.zeros(S, np.int32)
        self.calm = np.zeros(S, np.int32)
        self.anchor = np.zeros((S, 3))           # where a slot's calm began [mm]
        self.grab_off = np.zeros((S, 3))
        self.axis = np.zeros((S, 3))             # a distractor's axis, mesh frame
        self.base = np.zeros((S, 7))             # its second body's pose when affixed
        self.push = np.zeros((int(max_bodies), 7))
        self.body_slot = np.full(int(max_bodies), -1, np.int32)
        self._pushed = False
        self._any = False                        # some slot holds a rigid
        self._measuring = {}                     # body -> MeasureJob (large fragments)
        self._grab_after = set()                 # grabbed while being measured
        self.last_plate = -1                     # the plate placed last
        self.tool = np.zeros(3)
        self._cand = np.zeros(MAX_CAND, np.int32)
        self._cout = np.zeros(7)
        self._pm = np.zeros((3, 4))
        self._cur = np.zeros(7)
        self._com = np.zeros(3)

    # ------------------------------------------------------------- slots
    def clear(self) -> None:
        """Forget every rigid (a case reset)."""
        self.mode[:] = FREE
        self.owner[:] = -1
        self.host[:] = -1
        self.tag[:] = -1
        self.push[:] = 0.0
        self.body_slot[:] = -1
        self._pushed = False
        self._any = False
        self.last_plate = -1
        self._measuring.clear()
        self._grab_after.clear()

    @property
    def active(self) -> bool:
        """Some slot moves or follows a body."""
        return bool((self.mode >= DYNAMIC).any())

    def slot_of(self, b: int) -> int:
        """The slot of fragment body ``b`` (-1: none)."""
        return int(self.body_slot[b]) if 0 <= b < len(self.body_slot) else -1

    def _free_slot(self) -> int:
        """A free slot; when all are taken, the first sleeping fragment's (it
        keeps its pose and takes a slot again when next woken)."""
        free = np.flatnonzero(self.mode == FREE)
        if len(free) == 0:
            free = np.flatnonzero((self.mode == ASLEEP) & (self.kind == KIND_FRAGMENT))
            if len(free) == 0:
                raise ValueError(f"rigid: all {self.capacity} rigid slots are in use")
            self.body_slot[self.owner[free[0]]] = -1
            self.mode[free[0]] = FREE
            self.owner[free[0]] = -1
        return int(free[0])

    def _fill(self, s, smp, nrm, mass, com, inertia, k_n_mm) -> None:
        n = len(smp)
        self.smp[s, :n] = smp
        self.nrm[s, :n] = nrm
        self.n_smp[s] = n
        self.com_b[s] = com
        self.mass[s] = mass
        self.ib_inv[s] = np.linalg.inv(inertia)
        self.radius[s] = float(np.linalg.norm(smp - com, axis=1).max()) if n else 0.0
        self.k[s] = k_n_mm * N_TO_INTERNAL
        # critical damping of one sample carrying its share of the mass
        share = max(1.0, CONTACT_SHARE * n)
        self.c[s] = DAMPING_RATIO * 2.0 * math.sqrt(self.k[s] * mass / share)
        self.vel[s] = 0.0
        self.omg[s] = 0.0
        self.calm[s] = 0
        self.host[s] = -1
        self.tag[s] = -1
        self._any = True

    def wake_body(self, state, b: int, at_once: bool = False) -> int:
        """Let fragment ``b`` move (gravity, contact, the tool); returns its slot.

        Its samples and mass are computed now (from its current voxels) the
        first time; a sleeping fragment only wakes. A body a split job is
        still filling raises ``ValueError`` (it stays put until whole), and
        so does a large body the first time (:mod:`bonesim.engine.rigid_measure`:
        it is measured in slices by the next steps, and wakes when asked
        again after that), unless ``at_once``: then it is measured now, in
        one go (for callers outside the haptic loop: scripts, tests, tools).
        """
        if any(j.dst == b for j in getattr(state, "split_jobs", ())):
            raise ValueError(f"body {b} is still being split off "
                             "(bonesim.engine.split_jobs): it cannot move yet")
        s = self.slot_of(b)
        if s >= 0:
            if self.mode[s] == ASLEEP:
                self.mode[s] = DYNAMIC
                self.calm[s] = 0
            return s
        job = self._measuring.pop(b, None) if at_once else self._measuring.get(b)
        if job is None and not at_once and needs_slices(state, b):
            job = self._measuring[b] = MeasureJob(state, b)
        if job is not None and not at_once:
            if not job.done:
                raise ValueError(f"body {b} is being measured ({job.progress:.0%} of its "
                                 "box, bonesim.engine.rigid_measure): it moves once done")
            del self._measuring[b]
            d = job.result
        else:                                   # at once: the one-shot measurement
            d = body_samples(state, b, self.max_samples)
        s = self._free_slot()
        self._fill(s, d["smp"], d["nrm"], d["mass_kg"], d["com_mm"], d["inertia"],
                   FRAGMENT_STIFFNESS_N_MM_PER_KG * d["mass_kg"])
        self.kind[s] = KIND_FRAGMENT
        self.owner[s] = b
        self.body_slot[b] = s
        self.mode[s] = DYNAMIC
        return s

    def add_plate(self, pos, nrm, offset_mm: float, mass_kg: float, stiffness_n_mm: float,
                  pose, catalog: int = 0, axis=(1.0, 0.0, 0.0),
                  samples: int | None = None) -> int:
        """A plate (or distractor) mesh at ``pose`` (mesh-to-case), free to
        fall and rest on the bone; returns its slot.

        Parameters
        ----------
        pos, nrm : (n, 3) float
            Vertices [mm] and unit normals, mesh frame.
        offset_mm : float
            How far the samples sit out along the normals [mm].
        mass_kg, stiffness_n_mm : float
            Mass [kg]; contact stiffness per sample [N/mm].
        catalog : int
            Its index in the plate catalogue (recorded with its poses).
        axis : (3,) float
            A distractor's axis, mesh frame (which footplate holds which body
            and the direction :meth:`distract` moves the second body).
        samples : int, optional
            Contact samples kept (default and at most the set's ``max_samples``).
        """
        if not mass_kg > 0 or not stiffness_n_mm > 0:
            raise ValueError(f"plate: mass {mass_kg} kg and stiffness {stiffness_n_mm} "
                             "N/mm must be positive")
        keep = self.max_samples if samples is None else min(int(samples), self.max_samples)
        d = mesh_samples(pos, nrm, offset_mm, keep)
        pts = np.asarray(pos, np.float64).reshape(-1, 3)
        mass, com, inertia = mass_properties(pts, np.full(len(pts), mass_kg / len(pts)),
                                             max(offset_mm, 0.1))
        s = self._free_slot()
        self._fill(s, d["smp"], d["nrm"], mass, com, inertia, stiffness_n_mm)
        self.kind[s] = KIND_PLATE
        self.owner[s] = -1
        self.cat[s] = int(catalog)
        a = np.asarray(axis, np.float64)
        self.axis[s] = a / np.linalg.norm(a)
        self.rpose[s] = _unit_pose(pose)
        self.mode[s] = DYNAMIC
        self.last_plate = s
        return s

    def grab_body(self, state, b: int, tool_mm) -> None:
        """Fragment ``b`` follows the tool: now, or, while it is being
        measured (:mod:`bonesim.engine.rigid_measure`), at the step its
        measurement completes (where the tool is then)."""
        try:
            s = self.wake_body(state, b)
        except ValueError:
            if b not in self._measuring:
                raise
            self._grab_after.add(b)
            return
        self.grab(state, s, tool_mm)

    def grab(self, state, s: int, tool_mm) -> None:
        """Slot ``s`` follows the tool (kept at its present offset from it)."""
        self._check(s)
        if self.mode[s] == AFFIXED:
            raise ValueError(f"rigid: slot {s} is affixed to body {self.host[s]}")
        self.centre(s, state)
        self.grab_off[s] = self._com - np.asarray(tool_mm, np.float64)
        self.mode[s] = GRABBED
        self.calm[s] = 0

    def hold(self, b: int) -> None:
        """Fragment ``b`` was placed by hand (a ``MoveBody``): it stays where it
        was put (asleep, at rest) until the tool touches or grabs it again."""
        s = self.slot_of(b)
        if s >= 0 and self.mode[s] in (DYNAMIC, GRABBED):
            self.mode[s] = ASLEEP
            self.vel[s] = 0.0
            self.omg[s] = 0.0

    def release(self) -> int:
        """Every grabbed slot moves freely again; returns how many."""
        g = self.mode == GRABBED
        self.mode[g] = DYNAMIC
        self.calm[g] = 0
        return int(g.sum())

    def _check(self, s: int) -> None:
        if not 0 <= s < self.capacity or self.mode[s] == FREE:
            raise ValueError(f"rigid: slot {s} holds no rigid")

    def _pose_of(self, state, s: int) -> np.ndarray:
        return state.pose[self.owner[s]] if self.kind[s] == KIND_FRAGMENT else self.rpose[s]

    def centre(self, s: int, state=None) -> np.ndarray:
        """Slot ``s``'s centre of mass, case frame [mm] (a view, valid until
        the next call; ``state`` is needed for a fragment)."""
        p = self.rpose[s] if state is None or self.kind[s] == KIND_PLATE \
            else state.pose[self.owner[s]]
        if self.kind[s] == KIND_FRAGMENT and state is None:
            raise ValueError("rigid: a fragment's centre needs the state")
        pose_matrix_kernel(np.asarray(p, np.float64), self._pm)
        self._com[:] = self._pm[:, :3] @ self.com_b[s] + self._pm[:, 3]
        return self._com

    def samples_case(self, state, s: int) -> tuple:
        """Slot ``s``'s samples and normals in the case frame, ((n, 3), (n, 3))."""
        self._check(s)
        m = np.zeros((3, 4))
        pose_matrix_kernel(np.asarray(self._pose_of(state, s), np.float64), m)
        n = self.n_smp[s]
        return self.smp[s, :n] @ m[:, :3].T + m[:, 3], self.nrm[s, :n] @ m[:, :3].T

    def touching(self, state, s: int) -> np.ndarray:
        """How many of slot ``s``'s samples lie in each body's bone, (max_bodies,)."""
        pts, nrm = self.samples_case(state, s)
        # a little deeper than the sample, so a plate at rest counts
        pts = pts + 0.5 * state.grid.spacing_mm * nrm
        out = np.zeros(len(pts), np.int64)
        g = state.grid
        _sample_bodies(g.keys, g.vals, state.body, g.density, state.alive, state.pose_m,
                       g.origin_mm, g.spacing_mm, np.ascontiguousarray(pts), out)
        return np.bincount(out[out >= 0], minlength=len(state.alive))[:len(state.alive)]

    def affix(self, state, s: int) -> tuple:
        """Fix plate ``s`` to the body most of its samples touch: from now on
        it moves with that body. A distractor (slot with an ``axis`` whose
        footplates touch two bodies) is fixed to the body under its first
        footplate (negative side of its axis) and takes the other as its
        second body (:meth:`distract`). Returns ``(host, second)`` (-1: none).

        Raises
        ------
        ValueError
            The slot is not a plate, or touches no bone.
        """
        self._check(s)
        if self.kind[s] != KIND_PLATE:
            raise ValueError(f"rigid: slot {s} is not a plate")
        pts, nrm = self.samples_case(state, s)
        deep = np.ascontiguousarray(pts + 0.5 * state.grid.spacing_mm * nrm)
        hit = np.zeros(len(pts), np.int64)
        g = state.grid
        _sample_bodies(g.keys, g.vals, state.body, g.density, state.alive, state.pose_m,
                       g.origin_mm, g.spacing_mm, deep, hit)
        side = (self.smp[s, :self.n_smp[s]] - self.com_b[s]) @ self.axis[s]
        n_b = len(state.alive)
        if not (hit >= 0).any():
            raise ValueError(f"rigid: plate in slot {s} touches no bone")
        host = int(np.argmax(np.bincount(hit[(hit >= 0) & (side < 0)], minlength=n_b))) \
            if ((hit >= 0) & (side < 0)).any() else -1
        second = int(np.argmax(np.bincount(hit[(hit >= 0) & (side > 0)], minlength=n_b))) \
            if ((hit >= 0) & (side > 0)).any() else -1
        if host < 0:
            host, second = second, -1
        if second == host:
            second = -1
        # the plate's pose relative to its host: host^-1 o plate
        inv = _invert(state.pose[host])
        compose_poses(inv, self.rpose[s], self.rel[s])
        self.host[s] = host
        self.tag[s] = second
        if second >= 0:
            self.base[s] = state.pose[second]
        self.mode[s] = AFFIXED
        self.vel[s] = 0.0
        self.omg[s] = 0.0
        return host, second

    def distract(self, state, s: int, length_mm: float) -> np.ndarray:
        """Move an affixed distractor's second body ``length_mm`` along the
        distractor's axis (case frame) from where it was when affixed;
        returns the body's new pose (publish it with
        :func:`bonesim.engine.bodies.publish_pose`)."""
        self._check(s)
        if self.mode[s] != AFFIXED or self.tag[s] < 0:
            raise ValueError(f"rigid: slot {s} is not a distractor affixed across two "
                             "bodies")
        if self.tag[s] == 0:
            raise ValueError("rigid: the distractor's second footplate is on body 0, "
                             "which never moves (affix it the other way round)")
        m = np.zeros((3, 4))
        pose_matrix_kernel(self.rpose[s], m)
        out = self.base[s].copy()
        out[:3] += float(length_mm) * (m[:, :3] @ self.axis[s])
        return out

    def _measure_slice(self, state, tool_mm) -> None:
        """One slice of the first measurement under way; a grab that waited
        for it is carried out when it completes."""
        for b, job in self._measuring.items():
            if job.done:
                continue
            try:
                done = job.advance(state, measure_budget(), self.max_samples)
            except ValueError:                  # no bone left: nothing to move
                del self._measuring[b]
                self._grab_after.discard(b)
                return
            if done and b in self._grab_after:
                self._grab_after.discard(b)
                self.grab(state, self.wake_body(state, b), tool_mm)
            return

    # --------------------------------------------------------------- step
    def advance(self, state, t_s: float, tool_mm, drill: bool, tool_radius_mm: float,
                tool_gain_n_mm3: float) -> int:
        """One haptic step of rigid motion, before the haptic step of time ``t_s``.

        With the drill stopped the tool pushes every fragment it touches
        (waking it); every slot in motion takes :data:`SUBSTEPS` substeps;
        poses that changed are published (``POSE``, :data:`PLATE`) at
        ``t_s``. Without fragments and plates in motion this is a few
        comparisons.

        Returns
        -------
        int
            Poses published.
        """
        if self._measuring:                     # a large fragment: one slice per step
            self._measure_slice(state, tool_mm)
        many = not state._one_body
        if not many and not self._any:
            return 0
        self.tool[:] = tool_mm
        g = state.grid
        if many and not drill:
            n = tool_push_kernel(g.keys, g.vals, state.body, g.density, state.alive, state.pose_m,
                           state.bounds, g.origin_mm, g.spacing_mm, self.tool,
                           float(tool_radius_mm), float(tool_gain_n_mm3) * N_TO_INTERNAL,
                           1, self.push)
            self._pushed = n > 0
            if n:
                for b in range(1, len(self.push)):
                    if self.push[b, 6] > 0.0:
                        s = self.body_slot[b]
                        if s < 0 or self.mode[s] == ASLEEP:
                            try:
                                self.wake_body(state, b)
                            except ValueError:     # no slot left, or no bone: stays put
                                pass
        elif self._pushed:
            self.push[:] = 0.0
            self._pushed = False
        if not self.active:
            return 0
        ev = state.tissue.fields
        return int(advance_kernel(
            g.keys, g.vals, state.body, g.density, state.alive, state.pose, state.pose_m,
            state.bounds, g.origin_mm, g.spacing_mm, self.mode, self.kind, self.owner,
            self.host, self.cat, self.tag, self.rpose, self.rel, self.vel, self.omg,
            self.mass, self.ib_inv, self.com_b, self.k, self.c, self.radius, self.smp,
            self.nrm, self.n_smp, self.calm, self.anchor, self.grab_off, self.push,
            self.tool, self.gvec, self.h, SUBSTEPS, DRAG_TIME_S, FRICTION_COEFF,
            2 * math.pi * GRAB_HZ, SLEEP_MM, SLEEP_STEPS, MAX_SPEED_MM_S, float(t_s),
            ev["kind"], ev["body"], ev["label"], ev["t_s"], ev["ijk"], ev["n"], ev["value"],
            state.tissue.head, self._cand, self._cout, self._pm, self._cur, self._com))


def _unit_pose(pose) -> np.ndarray:
    p = np.asarray(pose, np.float64).copy()
    if p.shape != (7,) or not np.isfinite(p).all() or not np.linalg.norm(p[3:]) > 0:
        raise ValueError(f"rigid: a pose is (tx, ty, tz, qw, qx, qy, qz), got {p.tolist()}")
    p[3:] /= np.linalg.norm(p[3:])
    return p


def _invert(pose) -> np.ndarray:
    p = np.asarray(pose, np.float64)
    q = np.array([p[3], -p[4], -p[5], -p[6]])
    m = np.zeros((3, 4))
    pose_matrix_kernel(np.r_[0.0, 0.0, 0.0, q], m)
    return np.r_[-(m[:, :3] @ p[:3]), q]


def publish_plate(state, rs: RigidSet, s: int, t_s: float) -> None:
    """Publish plate slot ``s``'s present pose and attachment as a
    :data:`~bonesim.engine.events.PLATE` tissue event (placing, affixing;
    :meth:`RigidSet.advance` publishes its motion itself)."""
    from bonesim.engine.events import PLATE, push_event

    push_event(state.tissue, PLATE, float(t_s), body=s, label=int(rs.host[s]) + 1
               if rs.mode[s] == AFFIXED else 0, ijk=(int(rs.tag[s]) + 1, int(rs.mode[s]), 0),
               n=int(rs.cat[s]), value=rs.rpose[s])


def track_plates(ev: dict, plates: dict) -> bool:
    """Follow the plates in a batch of tissue events, in place.

    Parameters
    ----------
    ev : dict
        Tissue-event columns (:data:`bonesim.engine.events.TISSUE_FIELDS`).
    plates : dict
        Slot -> ``(catalogue index, (7,) pose, host body or -1)``; a
        ``RESET`` empties it.

    Returns
    -------
    bool
        Whether anything changed.
    """
    from bonesim.engine.events import PLATE, RESET

    kinds = np.asarray(ev["kind"])
    hit = np.flatnonzero((kinds == PLATE) | (kinds == RESET))
    for q in hit:
        if kinds[q] == RESET:
            plates.clear()
        else:
            plates[int(ev["body"][q])] = (int(ev["n"][q]), np.array(ev["value"][q, :7]),
                                          int(ev["label"][q]) - 1)
    return len(hit) > 0
