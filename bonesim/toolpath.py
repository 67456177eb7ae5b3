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
        Number of passes.
    margin_mm : float
        Least distance between the burr surface and any non-bone structure [mm].
    speed_mm_s : float
        Tool speed along the raster lines [mm/s].
    bite_mm : float
        How far the burr centre of the first pass sits below the first bone
        met along the approach [mm].
    sample_hz : float
        Rate of the written trajectory points [Hz] (``simulate`` interpolates).
    speed_rpm : float
        Spindle speed [rpm].
    """

    burr_radius_mm: float = 2.5
    region_radius_mm: float = 11.0
    line_overlap: float = 0.6
    layer_mm: float = 0.6
    n_layers: int = 6
    margin_mm: float = 1.0
    speed_mm_s: float = 12.0
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
    reach = np.linalg.norm(np.asarray(eye_mm, float) - focal) + 2 * np.linalg.norm(
        shape * spacing_mm)
    depth = np.arange(0.0, reach, step)
    eye = np.asarray(eye_mm, float)
    line_step = 2 * r * (1 - plan.line_overlap) if plan.line_overlap < 1 else r
    line_step = max(line_step, spacing_mm)
    along_step = plan.speed_mm_s / plan.sample_hz
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
    pts, drills = [], []

    def travel(p_from, p_to):
        n = max(int(np.ceil(np.linalg.norm(p_to - p_from) / along_step)), 1)
        for s in np.linspace(0, 1, n + 1)[1:]:
            pts.append(p_from + s * (p_to - p_from))
            drills.append(True)

    start = eye + lift * view
    pts.append(start)
    drills.append(False)
    for layer in range(plan.n_layers):
        d_layer = top - r + plan.bite_mm + layer * plan.layer_mm
        for n_line, a in enumerate(np.unique(cols[:, 0])):
            line = cols[cols[:, 0] == a]
            if n_line % 2:
                line = line[::-1]          # boustrophedon
            d = np.minimum(d_layer, line[:, 3])
            # only where the pass actually reaches below this column's surface
            line_pts = eye + line[:, 0:1] * u + line[:, 1:2] * v + d[:, None] * view
            first = line_pts[0]
            above = first.copy() - (d[0] - lift) * view
            travel(pts[-1], above)
            travel(above, first)
            for p in line_pts[1:]:
                pts.append(p)
                drills.append(True)
            travel(pts[-1], pts[-1] - (d[-1] - lift) * view)
    drills[-1] = False
    pos = np.array(pts)
    t = np.arange(len(pos)) / plan.sample_hz
    axis = np.repeat(view[None, :], len(pos), axis=0)
    return t, pos, axis, np.array(drills, bool)
