"""Tool paths planned from a case: the scripted demo mastoidectomy.

:func:`demo_mastoidectomy` plans a plausible saucerizing cortical
mastoidectomy for any case: the burr approaches along the case camera's
viewing direction (the surgeon's line of sight through the microscope) and
sweeps raster passes over the mastoid cortex, one layer deeper per pass, from
the surface down. Every tool-centre position keeps the burr's surface at
least ``margin_mm`` away from every structure that is not bone (sinus, dura,
facial nerve, chorda, labyrinth, ...): each raster column has a *floor*, the
deepest depth reachable from above without coming closer, so the cavity
becomes a saucer that approaches the danger structures without entering them.

The path is returned as a :class:`~bonesim.trajectory.Trajectory`
(case frame, mm) for ``bonesim simulate``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import BonesimError


@dataclass(frozen=True)
class DemoPlan:
    """Parameters of the demo mastoidectomy path (all lengths in mm).

    Attributes
    ----------
    burr_radius_mm : float
        Radius of the burr the path is planned for [mm].
    region_radius_mm : float
        Radius of the drilled disc around the camera's focal axis [mm].
    line_overlap : float
        Overlap of neighbouring raster lines, as a fraction of the burr
        diameter (lines are ``2 r (1 - overlap)`` apart).
    layer_mm : float
        Depth added per pass [mm].
    n_layers : int
        Largest number of passes (planning stops when a pass would cut nothing).
    column_mm : float
        Spacing of the planned points along a raster line [mm].
    margin_mm : float
        Least distance between the burr surface and any non-bone structure [mm].
    speed_mm_s : float
        Tool speed along the raster lines where the pass cuts [mm/s].
    travel_mm_s : float
        Tool speed in air and over columns already at their depth [mm/s].
    plunge_mm_s : float
        Tool speed entering and leaving a raster line [mm/s].
    bite_mm : float
        How far the burr centre of the first pass sits below the first bone
        met along the approach [mm].
    sample_hz : float
        Rate of the written trajectory points [Hz] (``simulate`` interpolates).
    speed_rpm : float
        Spindle speed [rpm].
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


def _frame(view):
    """Orthonormal (u, v) spanning the plane perpendicular to ``view``."""
    e = np.array([0.0, 0.0, 1.0]) if abs(view[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(e, view)
    u /= np.linalg.norm(u)
    return u, np.cross(view, u)


def demo_mastoidectomy(labels, spacing_mm, origin_mm, structures, eye_mm, focal_mm,
                       plan: DemoPlan = DemoPlan()):
    """Plan a layered saucerizing mastoidectomy.

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s >= 1`` is ``structures[s - 1]``).
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Case-frame centre of voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``kind``; every kind but "bone" is kept clear of.
    eye_mm, focal_mm : (3,) float
        The case camera; the approach runs from the eye toward the focal point.
    plan : DemoPlan

    Returns
    -------
    t_s : (n,) float64
        Times [s].
    pos_mm : (n, 3) float64
        Burr centre positions [mm].
    axis : (n, 3) float64
        Unit drill axis (handle toward tip), constant along the approach.
    drill : (n,) bool
        Drill running.
    """
    labels = np.asarray(labels)
    origin = np.asarray(origin_mm, float)
    kinds = np.array(["none"] + [s.kind for s in structures])
    is_bone = (kinds == "bone")[labels]
    danger = (kinds != "bone")[labels] & (labels > 0)
    if not is_bone.any():
        raise BonesimError("the case has no bone to drill")
    # distance [mm] from each voxel centre to the nearest danger voxel
    if danger.any():
        dist = ndimage.distance_transform_edt(~danger) * spacing_mm
    else:
        dist = np.full(labels.shape, np.inf)
    view = np.asarray(focal_mm, float) - np.asarray(eye_mm, float)
    if not np.linalg.norm(view) > 0:
        raise BonesimError("camera eye and focal point coincide")
    view /= np.linalg.norm(view)
    u, v = _frame(view)
    focal = np.asarray(focal_mm, float)
    r = plan.burr_radius_mm
    clear = r + plan.margin_mm
    shape = np.array(labels.shape)

    def lookup(vol, pts, outside):
        idx = np.floor((pts - origin) / spacing_mm + 0.5).astype(int)
        ok = np.all((idx >= 0) & (idx < shape), axis=-1)
        out = np.full(pts.shape[:-1], outside, dtype=vol.dtype)
        out[ok] = vol[tuple(idx[ok].T)]
        return out

    # depths along the approach, measured from the plane through the eye
    step = spacing_mm / 2
    eye = np.asarray(eye_mm, float)
    corners = origin + spacing_mm * (np.array(list(np.ndindex(2, 2, 2))) * (shape - 1))
    reach = np.linalg.norm(corners - eye, axis=1).max() + r   # far side of the volume
    depth = np.arange(0.0, reach, step)
    line_step = 2 * r * (1 - plan.line_overlap) if plan.line_overlap < 1 else r
    line_step = max(line_step, spacing_mm)
    along_step = plan.column_mm
    ws = np.arange(-plan.region_radius_mm, plan.region_radius_mm + 1e-9, line_step)
    cols = []           # (a, b, entry depth, floor depth)
    for a in ws:
        half = np.sqrt(max(plan.region_radius_mm ** 2 - a * a, 0.0))
        bs = np.arange(-half, half + 1e-9, along_step)
        for b in bs:
            base = eye + a * u + b * v
            ray = base + depth[:, None] * view
            hit = np.flatnonzero(lookup(is_bone.view(np.uint8), ray, 0))
            if hit.size == 0:
                continue
            entry = depth[hit[0]]
            unsafe = np.flatnonzero(lookup(dist, ray, np.inf) < clear)
            floor = depth[unsafe[0]] - step if unsafe.size else depth[-1]
            if floor > entry - r:        # the burr can reach this column's bone
                cols.append((a, b, entry, floor))
    if not cols:
        raise BonesimError("no bone lies under the camera's view of the target region")
    cols = np.array(cols)
    top = cols[:, 2].min()               # most lateral bone met in the region
    lift = top - r - 2.0                 # travel height, clear of all bone
    # waypoints with the speed [mm/s] used to reach each one
    pts = [eye + lift * view]
    speeds = [plan.travel_mm_s]
    drills = [False]

    def go(p, speed, drill=True):
        pts.append(p)
        speeds.append(speed)
        drills.append(drill)

    prev = np.full(len(cols), -np.inf)    # depth reached by the previous pass
    for layer in range(plan.n_layers):
        d_layer = top - r + plan.bite_mm + layer * plan.layer_mm
        depth_now = np.minimum(d_layer, cols[:, 3])
        # a column cuts in this pass if the burr reaches bone there and the
        # pass goes deeper than the previous one did
        cuts = (depth_now > cols[:, 2] - r) & (depth_now > prev + 1e-9)
        if not cuts.any():
            break
        for n_line, a in enumerate(np.unique(cols[:, 0])):
            on = np.flatnonzero((cols[:, 0] == a))
            if not cuts[on].any():
                continue
            if n_line % 2:
                on = on[::-1]              # boustrophedon
            line = eye + cols[on, 0:1] * u + cols[on, 1:2] * v + depth_now[on, None] * view
            first = on[0]
            go(line[0] - (depth_now[first] - lift) * view, plan.travel_mm_s)
            # down the column drilled by the previous pass quickly, then bite
            opened = max(prev[first], lift)
            if opened < depth_now[first]:
                go(line[0] - (depth_now[first] - opened) * view, plan.travel_mm_s)
            go(line[0], plan.plunge_mm_s)
            for q in range(1, len(on)):
                fast = not (cuts[on[q]] or cuts[on[q - 1]])
                go(line[q], plan.travel_mm_s if fast else plan.speed_mm_s)
            go(line[-1] - (depth_now[on[-1]] - lift) * view, plan.travel_mm_s)
        prev = depth_now
    drills[-1] = False
    pts = np.array(pts)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.array(speeds[1:])
    t_way = np.concatenate([[0.0], np.cumsum(seg)])
    # resample the waypoints at sample_hz (linear in time)
    t = np.arange(0.0, t_way[-1], 1.0 / plan.sample_hz)
    t = np.append(t, t_way[-1]) if t_way[-1] - t[-1] > 1e-9 else t
    pos = np.stack([np.interp(t, t_way, pts[:, c]) for c in range(3)], axis=1)
    # the drill state of the waypoint a sample is heading to
    nxt = np.minimum(np.searchsorted(t_way, t, side="left"), len(t_way) - 1)
    drill = np.array(drills, bool)[nxt]
    drill[0] = False
    axis = np.repeat(view[None, :], len(t), axis=0)
    return t, pos, axis, drill
