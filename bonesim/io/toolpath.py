"""Tool paths planned from a case: the scripted demo mastoidectomy.

:func:`demo_mastoidectomy` plans a plausible saucerizing cortical
mastoidectomy for any case (:func:`demo_trajectory` for a loaded case and a
burr): the burr approaches along the case camera's viewing direction (the
surgeon's line of sight through the microscope) and sweeps raster passes over
the mastoid cortex, one layer deeper per pass, from the surface down. The
plan's tunables are in ``bonesim/data/demo_plan.toml`` (:class:`DemoPlan`).

Margins at the source resolution
--------------------------------
Every burr-centre position of the plan keeps the burr's surface at least
``margin_mm`` from every structure that is not bone (sinus, dura, facial
nerve, chorda, labyrinth, ...), measured on the case's label map at the
resolution the data came in (:class:`bonesim.physics.clearance.Clearance`: exact
distances to the source voxels' boxes), not on the engine's grid:

* each raster column (a ray along the view) has a *floor*, the deepest depth
  its burr centre may reach. It is found by sphere tracing down the ray: the
  clearance ``D`` is 1-Lipschitz, so a step of ``D - c`` never passes a point
  closer than ``c = r + margin``; every depth above the floor is therefore
  clear. The cavity becomes a saucer that approaches the danger structures
  without entering them;
* the burr moves between neighbouring columns in stairs: straight along the
  view within a column (clear above its floor), and across only at a depth
  above both floors where the move is proven clear (bisection on the same
  Lipschitz bound), rising by :data:`STAIR_RAISE_MM` until it is;
* travel between raster lines happens on a plane above the bone that is
  checked clear over the whole region (a lattice of points, each with the
  extra clearance covering the gaps between them).

Irrigation and suction
----------------------
The trajectory's ``suction`` and ``irrigation`` columns (see
:mod:`bonesim.io.trajectory`) mark the samples during which the tool position
stands for the suction (irrigation) tip: the drill is off and the tool sweeps
the cavity without touching bone. After each layer that brings the drilling
time since the last rinse to ``rinse_every_s``, and after the last layer, the
plan rinses as a surgeon does: drill off, irrigate the cavity (a sweep over
every ``irrigation_every``-th raster line, ``irrigation_lift_mm`` above the
suction height), then suction it (a sweep over every raster line drilled so
far) just above the cut surface. The cut surface is estimated from the plan
(the first bone along each ray of a fine lattice, lowered where the burr
passed, by the burr's sphere shrunk by ``uncut_mm``: the voxels it only
grazed keep part of their density); the tool's sphere hovers
``rinse_gap_mm`` off it, rising over the cavity's walls.

The path is returned as a :class:`~bonesim.io.trajectory.Trajectory` (case
frame, mm) for ``bonesim simulate``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from bonesim.physics.clearance import Clearance
from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, read_toml
from bonesim.io.trajectory import Trajectory

__all__ = ["DemoPlan", "default_plan_path", "load_demo_plan", "demo_mastoidectomy",
           "demo_trajectory"]

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


@dataclass(frozen=True)
class DemoPlan:
    """Parameters of the demo mastoidectomy path (all lengths in mm).

    Attributes
    ----------
    burr_radius_mm : float
        Radius of the burr the path is planned for [mm] (from the burr).
    region_radius_mm : float
        Radius of the drilled disc around the camera's focal axis [mm].
    line_overlap : float
        Overlap of neighbouring raster lines, as a fraction of the burr
        diameter (lines are ``2 r (1 - overlap)`` apart).
    column_mm : float
        Spacing of the planned columns along a raster line [mm].
    layer_mm : float
        Depth added per pass [mm].
    n_layers : int
        Largest number of passes (planning stops when a pass would cut nothing).
    margin_mm : float
        Least distance between the burr surface and any non-bone structure,
        at the label map's source resolution [mm].
    speed_mm_s : float
        Tool speed along the raster lines where the pass cuts [mm/s].
    travel_mm_s : float
        Tool speed in air and over columns already at their depth [mm/s].
    plunge_mm_s : float
        Tool speed entering a raster line [mm/s].
    bite_mm : float
        How far the burr centre of the first pass sits below the first bone
        met along the approach [mm].
    sample_hz : float
        Rate of the written trajectory points [Hz] (``simulate`` interpolates).
    speed_rpm : float
        Spindle speed [rpm] (from the burr).
    rinse_every_s : float
        Drilling time after which the next layer's end brings a rinse [s].
    rinse_gap_mm : float
        Gap between the tool's sphere and the estimated cut surface while
        rinsing [mm].
    uncut_mm : float
        The cut is estimated as the burr's sphere shrunk by this much: the
        voxels the burr only grazed keep part of their density, and touch [mm].
    suction_mm_s : float
        Tool speed of the suction sweep [mm/s].
    irrigation_mm_s : float
        Tool speed of the irrigation sweep [mm/s].
    irrigation_lift_mm : float
        Height of the irrigation sweep above the suction sweep [mm].
    irrigation_every : int
        The irrigation sweep follows every this-many-th raster line.
    """

    burr_radius_mm: float = 2.5
    region_radius_mm: float = 9.0
    line_overlap: float = 0.5
    column_mm: float = 0.5
    layer_mm: float = 1.0
    n_layers: int = 20
    margin_mm: float = 1.0
    speed_mm_s: float = 20.0
    travel_mm_s: float = 60.0
    plunge_mm_s: float = 10.0
    bite_mm: float = 0.5
    sample_hz: float = 100.0
    speed_rpm: float = 60000.0
    rinse_every_s: float = 45.0
    rinse_gap_mm: float = 0.5
    uncut_mm: float = 1.0
    suction_mm_s: float = 40.0
    irrigation_mm_s: float = 60.0
    irrigation_lift_mm: float = 2.0
    irrigation_every: int = 2


#: Keys of ``demo_plan.toml`` (the burr gives its radius and speed).
_FILE_KEYS = tuple(f.name for f in fields(DemoPlan)
                   if f.name not in ("burr_radius_mm", "speed_rpm"))
#: Keys that are whole numbers >= 1.
_INTEGER_KEYS = ("n_layers", "irrigation_every")
#: Keys that must be > 0 (the others >= 0).
_POSITIVE_KEYS = ("region_radius_mm", "column_mm", "layer_mm", "speed_mm_s",
                  "travel_mm_s", "plunge_mm_s", "sample_hz", "rinse_every_s",
                  "suction_mm_s", "irrigation_mm_s")


def default_plan_path() -> Path:
    """Path of the shipped ``demo_plan.toml``."""
    from bonesim.resources import data_path

    return data_path("demo_plan.toml")


def load_demo_plan(path: str | Path | None = None) -> DemoPlan:
    """Read and check the ``[plan]`` table of a demo-plan file.

    Parameters
    ----------
    path : str or Path, optional
        Default: the shipped ``bonesim/data/demo_plan.toml``.

    Returns
    -------
    DemoPlan
        With the default burr radius and speed (:func:`demo_trajectory`
        replaces them by the burr's).

    Raises
    ------
    BonesimError
        Naming the file and the table for a missing, unknown or out-of-range
        key.
    """
    path = default_plan_path() if path is None else Path(path)
    doc = read_toml(path)
    check_keys(doc, ("plan",), path, "top level", required=("plan",))
    tab = doc["plan"]
    check_keys(tab, _FILE_KEYS, path, "plan", required=_FILE_KEYS)
    values = {}
    for name in _FILE_KEYS:
        integer = name in _INTEGER_KEYS
        v = get_number(tab, name, path, "plan", integer=integer,
                       minimum=1 if integer else 0.0,
                       maximum=0.99 if name == "line_overlap" else None)
        if not integer and (not math.isfinite(v) or (name in _POSITIVE_KEYS and v <= 0)):
            raise BonesimError(f"'{name}' must be a finite number > 0, got {v}", path,
                               "plan")
        values[name] = int(v) if integer else float(v)
    return DemoPlan(**values)


# --------------------------------------------------------------- geometry
def _frame(view):
    """Orthonormal (u, v) spanning the plane perpendicular to ``view``."""
    e = np.array([0.0, 0.0, 1.0]) if abs(view[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(e, view)
    u /= np.linalg.norm(u)
    return u, np.cross(view, u)


def _first_bone(is_bone, origin, spacing, base, view, depth, chunk=256):
    """Depth of the first bone voxel centre met along each ray ``base + t
    view`` sampled at ``depth`` (inf where none)."""
    shape = np.array(is_bone.shape)
    out = np.full(len(base), np.inf)
    for a in range(0, len(base), chunk):
        ray = base[a:a + chunk, None, :] + depth[None, :, None] * view
        idx = np.floor((ray - origin) / spacing + 0.5).astype(np.int64)
        ok = np.all((idx >= 0) & (idx < shape), axis=-1)
        hit = np.zeros(ok.shape, dtype=bool)
        hit[ok] = is_bone[tuple(idx[ok].T)]
        any_hit = hit.any(axis=1)
        out[a:a + chunk][any_hit] = depth[np.argmax(hit[any_hit], axis=1)]
    return out


def _trace_floors(dist, base, view, clear, t_max):
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


def _segment_clear(dist, p, q, clear) -> bool:
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


class _Path:
    """Waypoints, the speed [mm/s] used to reach each one and the tool's state
    on the way there (drill, suction, irrigation)."""

    def __init__(self, start):
        self.pts = [np.asarray(start, float)]
        self.speed = [1.0]
        self.state = [(False, False, False)]
        self.drill_s = 0.0

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
        if drill:
            self.drill_s += length / speed

    def sampled(self, rate_hz):
        """Samples at ``rate_hz`` (linear in time): t, pos, and the state of
        the waypoint each sample heads to."""
        pts = np.array(self.pts)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.array(self.speed[1:])
        t_way = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.arange(0.0, t_way[-1], 1.0 / rate_hz)
        t = np.append(t, t_way[-1]) if t_way[-1] - t[-1] > 1e-9 else t
        pos = np.stack([np.interp(t, t_way, pts[:, c]) for c in range(3)], axis=1)
        nxt = np.minimum(np.searchsorted(t_way, t, side="left"), len(t_way) - 1)
        state = np.array(self.state, dtype=bool)[nxt]
        state[0] = False
        return t, pos, state


# ---------------------------------------------------------------- planning
def demo_mastoidectomy(labels, spacing_mm, origin_mm, structures, eye_mm, focal_mm,
                       plan: DemoPlan = DemoPlan(),
                       clearance: Clearance | None = None) -> Trajectory:
    """Plan a layered saucerizing mastoidectomy with rinses between passes.

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel of the engine's grid (``s >= 1`` is
        ``structures[s - 1]``); where the bone lies.
    spacing_mm : float
        Grid voxel edge [mm].
    origin_mm : (3,) float
        Case-frame centre of grid voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``kind``; every kind but "bone" is kept clear of.
    eye_mm, focal_mm : (3,) float
        The case camera; the approach runs from the eye toward the focal point.
    plan : DemoPlan
    clearance : Clearance, optional
        Distances to the structures that are not bone, at the source
        resolution (:meth:`Clearance.from_native` of the case's
        ``native_labels``); default: measured on ``labels``.

    Returns
    -------
    Trajectory
        Burr centres [mm], the view as drill axis, drill / suction /
        irrigation states, ``plan.speed_rpm``, sampled at ``plan.sample_hz``.

    Raises
    ------
    BonesimError
        If the case has no bone, the camera's eye and focal point coincide, no
        bone lies under the view of the region, or no travel height above the
        bone is clear of the danger structures.
    ValueError
        If ``clearance`` lacks a structure that is not bone.
    """
    labels = np.asarray(labels)
    origin = np.asarray(origin_mm, float)
    spacing = float(spacing_mm)
    kinds = np.array(["none"] + [s.kind for s in structures])
    is_bone = (kinds == "bone")[labels]
    if not is_bone.any():
        raise BonesimError("the case has no bone to drill")
    danger = [s for s in range(1, len(kinds)) if kinds[s] != "bone"]
    if clearance is None:
        clearance = Clearance(labels, spacing, origin, danger)
    missing = sorted(set(danger) - set(clearance.structures))
    if missing:
        raise ValueError(f"the clearance field lacks structure(s) {missing}")
    groups = clearance.group_mask([danger])

    def dist(p):
        return clearance.distances(p, groups)[:, 0]

    view = np.asarray(focal_mm, float) - np.asarray(eye_mm, float)
    if not np.linalg.norm(view) > 0:
        raise BonesimError("camera eye and focal point coincide")
    view /= np.linalg.norm(view)
    u, v = _frame(view)
    eye = np.asarray(eye_mm, float)
    r = plan.burr_radius_mm
    clear = r + plan.margin_mm

    def at(a, b, d):
        return eye + np.multiply.outer(a, u) + np.multiply.outer(b, v) \
            + np.multiply.outer(d, view)

    # depths along the approach, measured from the plane through the eye
    shape = np.array(labels.shape)
    corners = origin + spacing * (np.array(list(np.ndindex(2, 2, 2))) * (shape - 1))
    reach = np.linalg.norm(corners - eye, axis=1).max() + r     # far side of the volume
    depth = np.arange(0.0, reach, spacing / 2)
    line_step = 2 * r * (1 - plan.line_overlap) if plan.line_overlap < 1 else r
    line_step = max(line_step, spacing)
    ca, cb = [], []
    for a in np.arange(-plan.region_radius_mm, plan.region_radius_mm + 1e-9, line_step):
        half = np.sqrt(max(plan.region_radius_mm ** 2 - a * a, 0.0))
        for b in np.arange(-half, half + 1e-9, plan.column_mm):
            ca.append(a)
            cb.append(b)
    ca, cb = np.array(ca), np.array(cb)
    entry = _first_bone(is_bone, origin, spacing, at(ca, cb, 0.0), view, depth)
    floor = _trace_floors(dist, at(ca, cb, 0.0), view, clear, reach)
    reachable = np.isfinite(entry) & (floor > entry - r)
    if not reachable.any():
        raise BonesimError("no bone lies under the camera's view of the target region")
    top = entry[reachable].min()                       # most lateral bone met
    lift = _travel_height(dist, at, plan, top - r - TRAVEL_ABOVE_MM, clear)

    def across(base0, base1, d):
        """The deepest depth from ``d`` up to the travel plane at which the
        straight move between the rays is proven clear."""
        while d > lift and not _segment_clear(dist, base0 + d * view, base1 + d * view,
                                              clear):
            d = max(d - STAIR_RAISE_MM, lift)
        return d

    keep = reachable & (floor > lift)
    ca, cb, entry, floor = ca[keep], cb[keep], entry[keep], floor[keep]
    surface = _Surface(is_bone, origin, spacing, eye, u, v, view, depth, plan)

    path = _Path(at(0.0, 0.0, lift))
    lines = np.unique(ca)
    prev = np.full(len(ca), -np.inf)     # depth free after the previous pass
    reached = np.full(len(ca), -np.inf)  # deepest burr centre in the column so far
    drilled_at_rinse = 0.0
    for layer in range(plan.n_layers):
        d_layer = top - r + plan.bite_mm + layer * plan.layer_mm
        depth_now = np.minimum(d_layer, floor)
        # a column cuts in this pass if the burr reaches bone there and the
        # pass goes deeper than the previous one did
        cuts = (depth_now > entry - r) & (depth_now > prev + 1e-9)
        if not cuts.any():
            break
        for n_line, a in enumerate(lines):
            on = np.flatnonzero(ca == a)
            if not cuts[on].any():
                continue
            if n_line % 2:
                on = on[::-1]              # boustrophedon
            first = on[0]
            path.go(at(a, cb[first], lift), plan.travel_mm_s, drill=True)
            # down the column drilled by the previous pass quickly, then bite
            opened = max(prev[first], lift)
            if opened < depth_now[first]:
                path.go(at(a, cb[first], opened), plan.travel_mm_s, drill=True)
            path.go(at(a, cb[first], depth_now[first]), plan.plunge_mm_s, drill=True)
            for q0, q1 in zip(on[:-1], on[1:]):
                fast = not (cuts[q0] or cuts[q1])
                speed = plan.travel_mm_s if fast else plan.speed_mm_s
                _stair(path, at(a, cb[q0], 0.0), at(a, cb[q1], 0.0), view,
                       depth_now[q0], depth_now[q1], speed, across, drill=True)
            path.go(at(a, cb[on[-1]], lift), plan.travel_mm_s, drill=True)
            surface.carve(a, cb[on], depth_now[on])
        visited = np.isin(ca, [a for a in lines if cuts[ca == a].any()])
        reached = np.where(visited, depth_now, reached)
        prev = depth_now        # lines not drilled: nothing to cut down to it either
        if path.drill_s - drilled_at_rinse >= plan.rinse_every_s:
            _rinse(path, surface, ca, cb, reached, floor, lift, at, view, dist, clear,
                   plan, across)
            drilled_at_rinse = path.drill_s
    if path.drill_s > drilled_at_rinse:
        _rinse(path, surface, ca, cb, reached, floor, lift, at, view, dist, clear, plan,
               across)

    t, pos, state = path.sampled(plan.sample_hz)
    n = len(t)
    return Trajectory(t_s=t, pos_mm=pos, axis=np.repeat(view[None, :], n, axis=0),
                      drill=state[:, 0], speed_rpm=np.full(n, plan.speed_rpm),
                      direction=np.ones(n, dtype=np.int8), suction=state[:, 1],
                      irrigation=state[:, 2])


def _stair(path, base0, base1, view, d0, d1, speed, across, **state):
    """From depth ``d0`` on ray ``base0`` to depth ``d1`` on ray ``base1``
    in stairs: along the view within a column, across at the shallower depth
    or higher, where ``across`` returns that depth proven clear."""
    d = across(base0, base1, min(d0, d1))
    path.go(base0 + d * view, speed, **state)
    path.go(base1 + d * view, speed, **state)
    path.go(base1 + d1 * view, speed, **state)


def _travel_height(dist, at, plan, start, clear):
    """The deepest depth from ``start`` upward (toward the eye, by
    :data:`TRAVEL_RAISE_MM`) whose plane is clear over the whole region: a
    lattice of points :data:`TRAVEL_LATTICE_MM` apart, each clear by half a
    lattice diagonal more."""
    g = TRAVEL_LATTICE_MM
    rad = plan.region_radius_mm + plan.column_mm
    ax = np.arange(-rad - g, rad + g + 1e-9, g)
    a, b = (x.ravel() for x in np.meshgrid(ax, ax, indexing="ij"))
    d = start
    while d >= 0.0:
        if np.all(dist(at(a, b, np.full(a.shape, d))) >= clear + g * math.sqrt(0.5)):
            return d
        d -= TRAVEL_RAISE_MM
    raise BonesimError("no travel height above the bone is clear of the structures "
                       "that are not bone")


class _Surface:
    """Estimate of the cavity's surface under the view: for each ray of a
    lattice ``column_mm`` apart covering the region and a burr radius
    around, the depth of the first bone (less a voxel), lowered where the
    burr passed (by its sphere shrunk by :attr:`DemoPlan.uncut_mm`)."""

    def __init__(self, is_bone, origin, spacing, eye, u, v, view, depth, plan):
        self.eye, self.u, self.v = eye, u, v
        self.r = plan.burr_radius_mm
        self.plan = plan
        g = plan.column_mm
        rad = plan.region_radius_mm + self.r + g
        ax = np.arange(-rad, rad + 1e-9, g)
        a, b = (x.ravel() for x in np.meshgrid(ax, ax, indexing="ij"))
        inside = a * a + b * b <= rad * rad
        self.a, self.b = a[inside], b[inside]
        base = eye + np.multiply.outer(self.a, u) + np.multiply.outer(self.b, v)
        entry = _first_bone(is_bone, origin, spacing, base, view, depth)
        self.depth = entry - spacing                   # the voxel's face, and the step
        self.carved = np.full(len(self.a), -np.inf)

    def carve(self, a, b, d):
        """The burr's centre passed at depths ``d`` over points ``(a, b)``."""
        rc = self.r - self.plan.uncut_mm                # the sphere that surely cut
        if rc <= 0.0:
            return
        for bb, dd in zip(b, d):
            rho2 = (self.a - a) ** 2 + (self.b - bb) ** 2
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
        return out - self.plan.rinse_gap_mm

    def height_under(self, pts):
        """:meth:`height` over the points' (n, 3) positions across the view."""
        rel = np.asarray(pts, float) - self.eye
        return self.height(rel @ self.u, rel @ self.v)


def _rinse(path, surface, ca, cb, reached, floor, lift, at, view, dist, clear, plan,
           across):
    """Drill off: irrigate the drilled cavity, then suction it (see the module
    docstring); back at the travel height after."""
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
            if k == 0 or not _hop(path, surface, at(a, cb[on[0]], 0.0), view, h[on[0]],
                                  dist, clear, speed, flag):
                path.go(path.last - np.dot(path.last - up, view) * view, plan.travel_mm_s)
                path.go(at(a, cb[on[0]], lift), plan.travel_mm_s)
                path.go(at(a, cb[on[0]], h[on[0]]), speed, **{flag: True})   # in, on
            for q0, q1 in zip(on[:-1], on[1:]):
                _stair(path, at(a, cb[q0], 0.0), at(a, cb[q1], 0.0), view, h[q0], h[q1],
                       speed, across, **{flag: True})
    path.go(path.last - np.dot(path.last - up, view) * view, plan.travel_mm_s)


def _hop(path, surface, base1, view, d1, dist, clear, speed, flag) -> bool:
    """From the path's last point to depth ``d1`` on ray ``base1`` in
    stairs, at a depth that keeps the tool off the estimated surface and
    clear of the danger structures; False (nothing added) where none does."""
    p0 = path.last
    d0 = float(np.dot(p0 - base1, view))
    base0 = p0 - d0 * view                       # the last point's ray, depth of base1
    n = max(2, int(math.ceil(np.linalg.norm(base1 - base0) / HOP_STEP_MM)) + 1)
    pts = base0 + np.multiply.outer(np.linspace(0.0, 1.0, n), base1 - base0)
    d = min(float(surface.height_under(pts).min()), d0, d1)
    if not np.isfinite(d) or not _segment_clear(dist, base0 + d * view, base1 + d * view,
                                                clear):
        return False
    for p in (base0 + d * view, base1 + d * view, base1 + d1 * view):
        path.go(p, speed, **{flag: True})
    return True


def demo_trajectory(case, burr, plan: DemoPlan | None = None) -> Trajectory:
    """The demo mastoidectomy of a loaded case for a burr.

    Parameters
    ----------
    case : bonesim.io.case.Case
        Its volume gives the bone (engine grid) and the structures' clearance
        (the label map at source resolution); its camera gives the approach.
    burr : str or Burr
        Burr name (``"cutting-5mm"``), path, or a loaded burr: its radius and
        default speed replace the plan's.
    plan : DemoPlan, optional
        Default: :func:`load_demo_plan` of the shipped file.

    Returns
    -------
    Trajectory
    """
    from bonesim.io.burrs import load_burr

    b = load_burr(burr) if isinstance(burr, (str, Path)) else burr
    plan = load_demo_plan() if plan is None else plan
    plan = replace(plan, burr_radius_mm=float(b.radius_mm),
                   speed_rpm=float(b.default_speed_rpm))
    vol = case.load_volume()
    cam = case.camera
    danger = [s for s, st in enumerate(case.structures, start=1) if st.kind != "bone"]
    clearance = Clearance.from_native(vol.native_labels, danger)
    return demo_mastoidectomy(vol.labels, vol.spacing_mm, vol.origin_mm, case.structures,
                              cam.eye_mm, cam.focal_mm, plan, clearance)
