"""Tool-path machinery for planned runs: burr-centre moves proven clear of
the structures, and the rinses between passes.

Everything works along rays of the surgeon's view: a ray is ``base + t
view`` with ``base`` on a plane through the eye and ``t`` the *depth* [mm]
along the unit viewing direction ``view`` (case frame, LPS [mm]).

Proofs of clearance
-------------------
A *gap function* ``gap(points) -> (n,)`` [mm] is 1-Lipschitz and is
positive where a tool centre may go (e.g. the distance to a structure less
the tool's radius and a margin, minimised over structures). Then

* :func:`trace_floors` sphere-traces each ray: a step of ``gap`` never passes
  a point where the gap is negative, so every depth above the returned
  *floor* is clear;
* :func:`segment_clear` proves a straight move clear by bisection on the
  same Lipschitz bound;
* :func:`stair` moves between two rays in stairs: along the view within a
  ray (clear above its floor), and across only at a depth proven clear.

Irrigation and suction
----------------------
:func:`rinse` sweeps the drilled cavity with the drill off: irrigation over
every ``irrigation_every``-th raster line ``irrigation_lift_mm`` above the
suction height, then suction over every line, the tool's sphere
``rinse_gap_mm`` off the estimated cut surface (:class:`CutSurface`: the
first bone along each ray, lowered where the burr passed, by its sphere
shrunk by ``uncut_mm``: the voxels it only grazed keep part of their
density).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.kernel_args import filled
from bonesim.errors import BonesimError

__all__ = ["TRACE_TOL_MM", "TRACE_STEPS", "TRAVEL_RAISE_MM", "TRAVEL_ABOVE_MM",
           "BISECT_MM", "HOP_STEP_MM", "STAIR_RAISE_MM", "view_frame", "first_bone",
           "trace_floors", "segment_clear", "segments_clear", "PathBuilder", "PathLongEnough",
           "stair", "stairs_along", "travel_height",
           "CutSurface", "rinse", "hop"]

#: Sphere tracing stops when a step would be shorter than this [mm].
TRACE_TOL_MM = 1e-3
#: Most sphere-tracing steps per ray (the depth reached so far stays clear).
TRACE_STEPS = 400
#: Spacing of the lattice on which the travel plane is checked clear [mm].
TRAVEL_LATTICE_MM = 1.0
#: How far the travel plane is raised toward the eye when it is not clear [mm].
TRAVEL_RAISE_MM = 2.0
#: Height of the travel plane above the most lateral bone of the region,
#: beyond the burr radius [mm].
TRAVEL_ABOVE_MM = 2.0
#: Straight moves are bisected down to this length before they count as not
#: clear [mm].
BISECT_MM = 0.01
#: Spacing of the points at which a hop between raster lines checks the
#: rinse height [mm].
HOP_STEP_MM = 0.25
#: How far a move across columns rises until it is proven clear [mm].
STAIR_RAISE_MM = 0.1


# --------------------------------------------------------------- geometry
def view_frame(view):
    """Orthonormal (u, v) spanning the plane perpendicular to ``view``."""
    e = np.array([0.0, 0.0, 1.0]) if abs(view[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(e, view)
    u /= np.linalg.norm(u)
    return u, np.cross(view, u)


def first_bone(is_bone, origin, spacing, base, view, depth):
    """Depth of the first bone voxel centre met along each ray ``base + t
    view`` sampled at ``depth`` (inf where none).

    Parameters
    ----------
    is_bone : (n0, n1, n2) bool
        Bone voxels, axes along the case frame's x, y, z.
    origin : (3,) float
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    spacing : float or (3,) float
        Voxel edge [mm].
    base : (n, 3) float
        Ray origins, case frame [mm].
    view : (3,) float
        Ray direction (unit).
    depth : (m,) float
        Depths sampled along each ray, increasing [mm].

    Returns
    -------
    (n,) float64
        The first sampled depth whose nearest voxel centre (rounded half
        up) lies in the volume and is bone [mm]; inf where none is.
    """
    bone = np.ascontiguousarray(is_bone, dtype=np.bool_)
    if bone.ndim != 3:
        raise ValueError(f"is_bone must be 3-D, got shape {bone.shape}")
    base = np.ascontiguousarray(np.asarray(base, np.float64).reshape(-1, 3))
    out = np.empty(len(base))
    _first_bone(bone, filled(origin, (3,), np.float64), filled(spacing, (3,), np.float64),
                base, filled(view, (3,), np.float64),
                np.ascontiguousarray(depth, dtype=np.float64), out)
    return out


@njit(cache=True, nogil=True)
def _first_bone(bone, origin, spacing, base, view, depth, out):
    n0, n1, n2 = bone.shape
    for r in range(base.shape[0]):
        out[r] = np.inf
        for q in range(depth.shape[0]):
            d = depth[q]
            i = math.floor((base[r, 0] + d * view[0] - origin[0]) / spacing[0] + 0.5)
            j = math.floor((base[r, 1] + d * view[1] - origin[1]) / spacing[1] + 0.5)
            k = math.floor((base[r, 2] + d * view[2] - origin[2]) / spacing[2] + 0.5)
            if 0 <= i < n0 and 0 <= j < n1 and 0 <= k < n2 and bone[i, j, k]:
                out[r] = d
                break


def trace_floors(dist, base, view, clear, t_max):
    """Deepest clear depth along each ray ``base + t view``, ``t`` in
    ``[0, t_max]``, by sphere tracing the clearance ``dist`` (a function of
    (n, 3) points) against ``clear``; -inf where the ray starts too close."""
    t = np.zeros(len(base))
    floor = np.full(len(base), np.nan)
    active = np.arange(len(base))
    for _ in range(TRACE_STEPS):
        if active.size == 0:
            break
        ta = t[active]
        gap = dist(base[active] + ta[:, None] * view) - clear
        stop = gap < TRACE_TOL_MM
        # (only the start can be too close: every later depth was stepped to)
        floor[active[stop]] = np.where((gap[stop] < 0.0) & (ta[stop] == 0.0), -np.inf,
                                       ta[stop])
        beyond = ~stop & (ta + gap >= t_max)
        floor[active[beyond]] = t_max
        go = ~stop & ~beyond
        t[active[go]] = ta[go] + gap[go]
        active = active[go]
    floor[active] = t[active]                     # out of steps: clear so far
    return floor


def segment_clear(dist, p, q, clear) -> bool:
    """Whether every point of the segment ``p q`` has clearance >= ``clear``
    (bisection on the 1-Lipschitz bound, exact up to :data:`BISECT_MM`)."""
    todo = [(np.asarray(p, float), np.asarray(q, float))]
    while todo:
        a, b = todo.pop()
        da, db = dist(np.stack([a, b]))
        length = float(np.linalg.norm(b - a))
        if da < clear or db < clear:
            return False
        if (da + db - length) / 2 >= clear:
            continue
        if length < BISECT_MM:
            return False
        m = (a + b) / 2
        todo += [(a, m), (m, b)]
    return True


def segments_clear(dist, p, q, clear) -> np.ndarray:
    """:func:`segment_clear` for many segments at once: ``(n,)`` bool, segment
    ``k`` from ``p[k]`` to ``q[k]`` ((n, 3) [mm]). The same bisection, every
    piece still open evaluated in one call per round."""
    p = np.asarray(p, float).reshape(-1, 3)
    q = np.asarray(q, float).reshape(-1, 3)
    ok = np.ones(len(p), bool)
    seg = np.arange(len(p))
    a, b = p, q
    while len(seg):
        d = dist(np.concatenate([a, b]))
        da, db = d[:len(seg)], d[len(seg):]
        length = np.linalg.norm(b - a, axis=1)
        bad = (da < clear) | (db < clear)
        done = ~bad & ((da + db - length) / 2 >= clear)
        short = ~bad & ~done & (length < BISECT_MM)
        ok[seg[bad | short]] = False
        go = ~bad & ~done & ~short & ok[seg]
        seg, a, b = seg[go], a[go], b[go]
        m = (a + b) / 2
        seg = np.concatenate([seg, seg])
        a, b = np.concatenate([a, m]), np.concatenate([m, b])
    return ok


class PathLongEnough(Exception):
    """Raised by :meth:`PathBuilder.go` once the path lasts past the
    builder's ``until_s``: the planner stops there."""


class PathBuilder:
    """Waypoints, the speed [mm/s] used to reach each one and the tool's state
    on the way there (drill, suction, irrigation; the burr index ``burr``
    held when the waypoint was added).

    ``until_s`` [s]: :meth:`go` raises :class:`PathLongEnough` once the path
    lasts longer than that by more than ``margin_s`` (a sample interval or
    two). Every waypoint before then is as without the limit, so the samples
    up to ``until_s`` (:meth:`sampled`, linear between waypoints) are those
    of the whole path.
    """

    def __init__(self, start, until_s: float | None = None, margin_s: float = 0.0):
        self.pts = [np.asarray(start, float)]
        self.speed = [1.0]
        self.state = [(False, False, False)]
        self.burrs = [0]
        self.burr = 0                       # burr index of the moves to come
        self.drill_s = 0.0
        self.t_s = 0.0                      # the path's duration so far [s]
        self.stop_s = math.inf if until_s is None else float(until_s) + float(margin_s)

    @property
    def last(self):
        return self.pts[-1]

    def go(self, p, speed, drill=False, suction=False, irrigation=False):
        p = np.asarray(p, float)
        length = float(np.linalg.norm(p - self.pts[-1]))
        if length <= 1e-9:
            return
        self.pts.append(p)
        self.speed.append(float(speed))
        self.state.append((bool(drill), bool(suction), bool(irrigation)))
        self.burrs.append(self.burr)
        if drill:
            self.drill_s += length / speed
        self.t_s += length / float(speed)
        if self.t_s > self.stop_s:
            raise PathLongEnough

    def sampled(self, rate_hz):
        """Samples at ``rate_hz`` (linear in time): t, pos, the state (drill,
        suction, irrigation) and the burr of the waypoint each sample heads
        to."""
        pts = np.array(self.pts)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.array(self.speed[1:])
        t_way = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.arange(0.0, t_way[-1], 1.0 / rate_hz)
        t = np.append(t, t_way[-1]) if t_way[-1] - t[-1] > 1e-9 else t
        pos = np.stack([np.interp(t, t_way, pts[:, c]) for c in range(3)], axis=1)
        nxt = np.minimum(np.searchsorted(t_way, t, side="left"), len(t_way) - 1)
        state = np.array(self.state, dtype=bool)[nxt]
        state[0] = False
        burr = np.array(self.burrs, dtype=np.int64)[nxt]
        return t, pos, state, burr



def stair(path, base0, base1, view, d0, d1, speed, across, **state):
    """From depth ``d0`` on ray ``base0`` to depth ``d1`` on ray ``base1``
    in stairs: along the view within a column, across at the shallower depth
    or higher, where ``across`` returns that depth proven clear."""
    d = across(base0, base1, min(d0, d1))
    path.go(base0 + d * view, speed, **state)
    path.go(base1 + d * view, speed, **state)
    path.go(base1 + d1 * view, speed, **state)


def stairs_along(path, bases, depths, view, speed, gap, lift, **state):
    """:func:`stair` through consecutive rays ``bases`` (n, 3) at ``depths``
    (n,) [mm]: each move across at the shallower of its two depths where that
    is proven clear (:func:`segments_clear`, all at once), else raised by
    :data:`STAIR_RAISE_MM` until it is (not above ``lift``)."""
    bases = np.asarray(bases, float)
    depths = np.asarray(depths, float)
    if len(bases) < 2:
        return
    d = np.minimum(depths[:-1], depths[1:])
    ok = segments_clear(gap, bases[:-1] + d[:, None] * view, bases[1:] + d[:, None] * view,
                        0.0)
    bad = np.flatnonzero(~ok)
    if len(bad):
        # raise each refused move by STAIR_RAISE_MM steps up to the travel
        # depth, every candidate of every move proven in one batch; the deepest
        # clear one is taken (the travel depth itself is clear)
        steps = np.ceil(np.maximum(d[bad] - lift, 0.0) / STAIR_RAISE_MM).astype(int)
        k = np.concatenate([np.arange(1, n + 1) for n in steps]) if steps.sum() else \
            np.zeros(0, int)
        owner = np.repeat(np.arange(len(bad)), steps)
        cand = np.maximum(d[bad][owner] - STAIR_RAISE_MM * k, lift)
        i0, i1 = bad[owner], bad[owner] + 1
        clear = segments_clear(gap, bases[i0] + cand[:, None] * view,
                               bases[i1] + cand[:, None] * view, 0.0) | (cand <= lift)
        best = np.full(len(bad), lift)
        for j in range(len(bad)):
            sel = np.flatnonzero((owner == j) & clear)
            if len(sel):
                best[j] = cand[sel[0]]                       # the deepest clear one
        d[bad] = best
    for k in range(len(d)):
        path.go(bases[k] + d[k] * view, speed, **state)
        path.go(bases[k + 1] + d[k] * view, speed, **state)
        path.go(bases[k + 1] + depths[k + 1] * view, speed, **state)


def travel_height(gap, at, a, b, start):
    """The deepest depth from ``start`` upward (toward the eye, by
    :data:`TRAVEL_RAISE_MM`) whose plane is clear over the region: the
    points ``(a, b)`` [mm] across the view (a lattice :data:`TRAVEL_LATTICE_MM`
    apart at most), each clear by half a lattice diagonal more.

    Raises
    ------
    BonesimError
        No depth from ``start`` up to the eye is clear.
    """
    g = TRAVEL_LATTICE_MM
    d = start
    while d >= 0.0:
        if np.all(gap(at(a, b, np.full(np.shape(a), d))) >= g * math.sqrt(0.5)):
            return d
        d -= TRAVEL_RAISE_MM
    raise BonesimError("no travel height above the bone is clear of the structures "
                       "that are not bone")


class CutSurface:
    """Estimate of the cavity's surface under the view: for each ray ``(a,
    b)`` [mm] of a lattice covering the drilled region and a tool radius
    around it, the depth of the first bone (less a voxel), lowered where a
    burr passed (by its sphere shrunk by ``uncut_mm``).

    Parameters
    ----------
    is_bone : (nx, ny, nz) bool
        Bone on the engine's grid.
    origin, spacing
        The grid's origin [mm] and voxel edge [mm].
    eye, u, v, view : (3,) float
        The rays' plane and direction (``base = eye + a u + b v``).
    depth : (m,) float
        Depths sampled along the rays for the first bone [mm].
    a, b : (n,) float
        The lattice [mm].
    radius_mm : float
        Radius of the rinsing tool's sphere [mm].
    uncut_mm : float
        How much smaller than a burr the surely cut sphere is [mm].
    gap_mm : float
        Gap kept between the tool's sphere and the surface [mm].
    """

    def __init__(self, is_bone, origin, spacing, eye, u, v, view, depth, a, b,
                 radius_mm, uncut_mm, gap_mm):
        self.eye, self.u, self.v = eye, u, v
        self.r = float(radius_mm)
        self.uncut = float(uncut_mm)
        self.gap = float(gap_mm)
        self.a, self.b = np.asarray(a, float), np.asarray(b, float)
        base = eye + np.multiply.outer(self.a, u) + np.multiply.outer(self.b, v)
        entry = first_bone(is_bone, origin, spacing, base, view, depth)
        self.depth = entry - spacing                   # the voxel's face, and the step
        self.carved = np.full(len(self.a), -np.inf)

    def carve(self, a, b, d, radius_mm):
        """A burr of ``radius_mm`` passed with its centre at depths ``d`` over
        points ``(a, b)`` [mm]."""
        rc = float(radius_mm) - self.uncut              # the sphere that surely cut
        if rc <= 0.0:
            return
        for aa, bb, dd in zip(np.broadcast_to(a, np.shape(d)), b, d):
            rho2 = (self.a - aa) ** 2 + (self.b - bb) ** 2
            near = rho2 < rc * rc
            low = dd + np.sqrt(rc * rc - rho2[near])
            self.carved[near] = np.maximum(self.carved[near], low)

    def height(self, a, b):
        """Deepest depths of the tool's centre over points ``(a, b)`` that
        keep its sphere ``rinse_gap_mm`` off the estimated surface."""
        r = self.r
        surf = np.maximum(self.depth, self.carved)
        out = np.full(np.shape(a), np.inf)
        for q, (aa, bb) in enumerate(zip(np.ravel(a), np.ravel(b))):
            rho2 = (self.a - aa) ** 2 + (self.b - bb) ** 2
            near = rho2 < r * r
            if near.any():
                out.flat[q] = np.min(surf[near] - np.sqrt(r * r - rho2[near]))
        return out - self.gap

    def height_under(self, pts):
        """:meth:`height` over the points' (n, 3) positions across the view."""
        rel = np.asarray(pts, float) - self.eye
        return self.height(rel @ self.u, rel @ self.v)


def rinse(path, surface, ca, cb, reached, floor, lift, at, view, gap, plan):
    """Drill off: irrigate the drilled cavity, then suction it (see the module
    docstring); back at the travel height after.

    ``ca, cb`` [mm] are the lattice columns swept (raster lines of equal
    ``ca``), ``reached`` the deepest burr centre per column (-inf where the
    burr never went), ``floor`` the deepest clear tool centre, ``gap`` the
    gap function the moves keep positive, ``lift`` the travel depth."""
    opened = np.isfinite(reached)
    lines = np.unique(ca[opened])
    if lines.size == 0:
        return
    # never deeper than the burr went, nor than the column's floor
    height = np.minimum(np.minimum(surface.height(ca, cb), floor), reached)
    sweeps = []
    for n_line, a in enumerate(lines):
        on = np.flatnonzero((ca == a) & opened)
        sweeps.append(on[::-1] if n_line % 2 else on)
    irrigate = sweeps[::plan.irrigation_every]
    suction = [s[::-1] for s in sweeps[::-1]]           # back, still boustrophedon
    higher = np.minimum(np.maximum(height - plan.irrigation_lift_mm, lift), height)
    up = at(0.0, 0.0, lift)                              # a point of the travel plane
    for cols, h, speed, flag in ((irrigate, higher, plan.irrigation_mm_s, "irrigation"),
                                 (suction, height, plan.suction_mm_s, "suction")):
        for k, on in enumerate(cols):
            a = ca[on[0]]
            if k == 0 or not hop(path, surface, at(a, cb[on[0]], 0.0), view, h[on[0]],
                                 gap, 0.0, speed, flag):
                path.go(path.last - np.dot(path.last - up, view) * view, plan.travel_mm_s)
                path.go(at(a, cb[on[0]], lift), plan.travel_mm_s)
                path.go(at(a, cb[on[0]], h[on[0]]), speed, **{flag: True})   # in, on
            stairs_along(path, at(np.full(len(on), a), cb[on], 0.0), h[on], view, speed,
                         gap, lift, **{flag: True})
    path.go(path.last - np.dot(path.last - up, view) * view, plan.travel_mm_s)


def hop(path, surface, base1, view, d1, dist, clear, speed, flag) -> bool:
    """From the path's last point to depth ``d1`` on ray ``base1`` in
    stairs, at a depth that keeps the tool off the estimated surface and
    clear of the danger structures; False (nothing added) where none does."""
    p0 = path.last
    d0 = float(np.dot(p0 - base1, view))
    base0 = p0 - d0 * view                       # the last point's ray, depth of base1
    n = max(2, int(math.ceil(np.linalg.norm(base1 - base0) / HOP_STEP_MM)) + 1)
    pts = base0 + np.multiply.outer(np.linspace(0.0, 1.0, n), base1 - base0)
    d = min(float(surface.height_under(pts).min()), d0, d1)
    if not np.isfinite(d) or not segment_clear(dist, base0 + d * view, base1 + d * view,
                                                clear):
        return False
    for p in (base0 + d * view, base1 + d * view, base1 + d1 * view):
        path.go(p, speed, **{flag: True})
    return True

