"""A cortical mastoidectomy planned from the landmarks, as a surgeon drills it.

The plan (:func:`plan_case`, via :func:`bonesim.io.toolpath.plan_mastoidectomy`)
follows ``../shared/MASTOIDECTOMY.md``; its parameters are the tables of
``bonesim/data/demo_plan.toml`` (:class:`bonesim.io.toolpath.DemoPlan`).

Frame
-----
Case frame, LPS [mm]. The burr approaches along the case camera's viewing
direction ``view`` (the surgeon's line of sight); positions across it are
``(a, b)`` [mm] on the plane through the eye (``base = eye + a u + b v``,
:func:`bonesim.io.path_moves.view_frame`) and *depth* ``t`` [mm] runs along
``view``. A lattice of rays ``column_mm`` apart covers the cavity: the
*columns*.

The cavity
----------
1. **Outline** (the triangle of attack): in the ``(y, z)`` plane of the
   cortex, the line ``canal_wall_mm`` behind the ear canal's posterior wall
   (front), the tegmen's height less ``tegmen_keep_mm`` (top, the temporal
   line), and the sigmoid sinus's anterior edge less ``sinus_keep_mm`` at
   each height (back), down to ``tip_keep_mm`` above the mastoid tip; lifted
   onto the cortex and projected across the view. ``region_radius_mm`` > 0
   also keeps it within a disc around the camera's focal axis.
2. **Saucer**: the cut surface may go at most ``wall_slope`` mm deeper per mm
   inward from the outline (the cortical rim bevelled; a burr's centre sits
   ``r sqrt(1 + slope^2)`` above that wall, so its sphere touches the wall and
   never overhangs it), and no deeper than the antrum's centre plus
   ``below_antrum_mm`` (the cavity is deepened to the antrum, opening it).
3. **Margins** at the source resolution: each column's *floor* is the deepest
   burr centre whose sphere keeps its margin from every structure that is
   not bone (:mod:`bonesim.io.path_moves` proves it by sphere tracing the exact
   distances of :class:`bonesim.physics.clearance.Clearance`): critical
   structures (nerves, labyrinth, ossicles), the *thin* structures whose bone
   is thinned (sigmoid sinus, dura; merged labels too) and the ear canal
   (labelled, or a capsule along the canal found in the cortex, radius as
   found) each have their margin per burr; bone within ``edge_mm`` of the
   volume's faces is never touched.

Two burrs
---------
The cutting burr (burr 0, ``[bulk]`` margins) removes the bulk: passes
``layer_mm`` deep from the cortex down to its targets. The finishing burr
(burr 1: the smaller diamond ``finish_burr``, ``[finish]`` margins; or the
cutting burr itself for a one-burr plan) then works where a structure, not
the saucer's wall nor the antrum's depth, stopped the cutting burr, and its
closer margins let its bottom go at least ``finish_gain_mm`` deeper than the
cutting burr's did in that column (along the walls, what it then cuts is the
bone it thins sideways): the bone over
the sinus and the tegmen is thinned until their colour shows and the cavity
finished near the nerves and the labyrinth, in ``finish_layer_mm`` passes at
``finish_speed_mm_s``. The burr is changed with the drill off at the travel
height.

Strokes along the walls
-----------------------
Each pass cuts the columns whose depth it deepens. Its strokes are the
contour lines of the distance from the pass's edge, ``2 r (1 - line_overlap)``
apart, outermost first (:func:`strokes`): they run parallel to the cavity's
walls and so along the structures that shape them, and each move from one
stroke to the next goes inward, away from the walls, never toward them. A
stroke starts where its columns lie furthest above their floors. Points are
the lattice columns along the contour; moves between columns go in stairs
proven clear (:func:`bonesim.io.path_moves.stair`).

Rinses as before: after a pass that brings the drilling time since the last
rinse to ``rinse_every_s``, and at the end.
"""
from __future__ import annotations

import math

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.landmarks import analysis_grid, structure_groups
from bonesim.io.path_moves import (TRAVEL_ABOVE_MM, STAIR_RAISE_MM, CutSurface,
                                   PathBuilder, PathLongEnough, first_bone, rinse,
                                   segment_clear, stair, stairs_along, trace_floors,
                                   travel_height, view_frame)
from bonesim.io.recent import Recent
from bonesim.io.trajectory import Trajectory

__all__ = ["THIN_GROUPS", "CANAL_GROUPS", "NEEDED", "plan_case", "mastoidectomy_path",
           "strokes", "danger_groups"]

#: Landmark groups whose bone the plan thins (sinus and dura, merged or not).
THIN_GROUPS = ("sinus", "tegmen", "dura")
#: Soft landmark groups kept at the canal's margin (ear canal, middle-ear air).
CANAL_GROUPS = ("ear_canal", "middle_ear")
#: Landmarks the plan cannot do without.
NEEDED = ("ear_canal", "tegmen", "antrum")
_debug: dict = {}
#: Moves between strokes longer than this many stroke spacings go by the
#: travel height rather than in stairs.
_FAR_STROKES = 2.0


def danger_groups(structures) -> tuple[list, list, list]:
    """Structure indices (1-based) kept clear: ``(critical, thin, canal)``.

    Thin: sinus and dura (any structure of those groups, merged labels
    included); canal: soft structures of the ear canal and middle ear;
    critical: every other structure that is not bone.
    """
    groups = structure_groups(structures)
    crit, thin, canal = [], [], []
    for s, (st, g) in enumerate(zip(structures, groups), start=1):
        if st.kind == "bone":
            continue
        if st.kind != "critical" and g & set(THIN_GROUPS):
            thin.append(s)
        elif st.kind == "soft" and g & set(CANAL_GROUPS):
            canal.append(s)
        else:
            crit.append(s)
    return crit, thin, canal


def plan_case(case, plan, two_burrs: bool = True, until_s: float | None = None):
    """The mastoidectomy of a loaded case (see the module docstring).

    Parameters
    ----------
    case : bonesim.io.case.Case
    plan : bonesim.io.toolpath.DemoPlan
        With the burrs' radii and speeds filled in.
    two_burrs : bool
        Finish with burr 1 (else with burr 0).
    until_s : float, optional
        Plan only the first ``until_s`` [s] of the run: the samples at times up
        to ``until_s`` are exactly those of the whole plan (see
        :func:`mastoidectomy_path`).

    Returns
    -------
    trajectory : Trajectory
    summary : dict

    Raises
    ------
    BonesimError
        Naming the case and the landmark the plan needs but could not find.

    Notes
    -----
    The plan is a function of the case and the plan's values alone. For a
    phantom case (its volume generated from the manifest's values, no file
    that could change) the process keeps the last :data:`CACHED_PLANS` whole
    plans (not those cut at ``until_s``) and returns a copy: the tools that
    drill the demo plan again and again plan it once.
    """
    import copy

    if case.volume.format != "phantom" or until_s is not None:
        return _plan_case(case, plan, two_burrs, until_s)
    key = (case, plan, bool(two_burrs))
    done = _plans.get(key)
    if done is None:
        done = _plan_case(case, plan, two_burrs, until_s)
        _plans.put(key, done)
    return copy.deepcopy(done)


#: Plans of phantom cases :func:`plan_case` keeps for the process's later calls.
CACHED_PLANS = 4
_plans = Recent(CACHED_PLANS)


def _plan_case(case, plan, two_burrs, until_s):
    """:func:`plan_case`, planned."""
    from bonesim.physics.clearance import Clearance

    vol = case.load_volume()
    lm = case.landmarks
    lacking = [n for n in NEEDED if lm.get(n) is None]
    if lacking:
        why = "; ".join(lm.missing) or "not found"
        raise BonesimError(f"no demo mastoidectomy: the plan needs the "
                           f"{', '.join(n.replace('_', ' ') for n in lacking)} ({why})",
                           case.manifest)
    danger = [s for s, st in enumerate(case.structures, start=1) if st.kind != "bone"]
    clearance = Clearance.from_native(vol.native_labels, danger)
    cam = case.camera
    try:
        return mastoidectomy_path(vol.labels, vol.spacing_mm, vol.origin_mm,
                                  case.structures, lm, cam.eye_mm, cam.focal_mm, plan,
                                  clearance, two_burrs, until_s)
    except BonesimError as exc:
        if exc.path is None:
            raise BonesimError(exc.message, case.manifest) from None
        raise


# ------------------------------------------------------------------ outline
def _sinus_rim_profile(lm, z_levels, slope):
    """Where the saucer's back rim must lie at each height for its wall to
    reach the sigmoid sinus: the least ``y + depth / slope`` over the
    sinus's voxels within a mm of the height [mm] (``depth`` [mm] under the
    cortex at the voxel's column), lateral to the antrum's depth less 2 mm;
    NaN where the sinus is absent. A wall of that slope from there passes
    the sinus, so there the structure, not the wall, sets the depth."""
    m = lm.masks.get("sinus")
    out = np.full(len(z_levels), np.nan)
    if m is None:
        return out
    h, origin = lm.cortex["h"], lm.cortex["origin_mm"]
    pts = origin + h * np.argwhere(m)
    lat = 1.0 if lm.side == "left" else -1.0
    ant = lm.point("antrum")
    pts = pts[lat * pts[:, 0] >= lat * ant[0] - 2.0]
    for q, z in enumerate(z_levels):
        sl = pts[np.abs(pts[:, 2] - z) <= 1.0]
        if len(sl):
            depth = lat * (_cortex_x(lm, sl[:, 1], sl[:, 2]) - sl[:, 0])
            out[q] = np.percentile(sl[:, 1] + np.maximum(depth, 0.0) / slope, 5)
    return out


def _outline_yz(lm, plan, volume_lo, volume_hi):
    """The triangle of attack: a (y, z) polygon [mm] on the cortex and, per
    edge (vertex ``k`` to ``k + 1``), the slope of the wall below it.

    Front (behind the canal's wall, around its posterosuperior rim, above it
    to the tegmen's line: Macewen's triangle in the anterosuperior corner) and
    top (the tegmen's line) have steep walls (``steep_slope``: they follow
    the canal and the tegmen in); the back
    (over the sinus: ``sinus_over_mm`` behind the rim whose wall reaches the
    sinus, :func:`_sinus_rim_profile`) and the bottom (toward the tip) are
    saucerized (``wall_slope``), but where the volume's face cuts the back
    rim off, its wall too goes straight in.
    """
    canal = lm.get("ear_canal")
    wall = canal.detail["posterior_wall_y_mm"]
    y_front = wall + plan.canal_wall_mm
    z_top = lm.get("tegmen").point_mm[2] - plan.tegmen_keep_mm
    z_top = min(z_top, volume_hi[2] - plan.edge_mm)
    tip = lm.get("mastoid_tip")
    z_low = (tip.point_mm[2] if tip is not None else canal.point_mm[2] - 10.0) \
        + plan.tip_keep_mm
    z_low = max(z_low, volume_lo[2] + plan.edge_mm)
    if z_top - z_low < 4.0:
        raise BonesimError(f"no room for a mastoidectomy: the tegmen's line (z {z_top:.1f} "
                           f"mm) lies within 4 mm of the mastoid's lowest point "
                           f"(z {z_low:.1f} mm)")
    zs = np.linspace(z_top, z_low, max(3, int(math.ceil((z_top - z_low) / 2.0)) + 1))
    rim = _sinus_rim_profile(lm, zs, plan.wall_slope)
    sinus = lm.get("sigmoid_sinus")
    default = sinus.point_mm[1] if sinus is not None else wall + 20.0
    back = np.where(np.isfinite(rim), rim, default) + plan.sinus_over_mm
    # where the volume's face cuts the rim off, the wall goes straight in (to
    # reach the sinus at all without touching the bone at the edge)
    clipped = back > volume_hi[1] - plan.edge_mm
    back = np.minimum(back, volume_hi[1] - plan.edge_mm)
    if np.max(back) - y_front < 4.0:
        raise BonesimError(f"no room for a mastoidectomy: the sinus's front (y "
                           f"{np.max(back) - plan.sinus_over_mm:.1f} mm) lies within "
                           f"{4.0 - plan.sinus_over_mm:g} mm of the ear canal's "
                           f"posterior wall (y {wall:.1f} mm)")
    # the front: behind the canal's wall below its axis, then around its
    # posterosuperior rim (Macewen's triangle lies above it, in the cavity's
    # anterosuperior corner) up to the line over the canal's axis
    y_c, z_c = canal.point_mm[1], canal.point_mm[2]
    r_rim = canal.detail["radius_mm"] + plan.canal_wall_mm
    angles = np.linspace(0.0, 0.5 * math.pi, 7)
    arc = [(y_c + r_rim * math.cos(a), z_c + r_rim * math.sin(a)) for a in angles
           if z_c + r_rim * math.sin(a) < z_top]
    steep, saucer = plan.steep_slope, plan.wall_slope
    poly = [(min(y_c, y_front), z_top)] + \
        [(max(b, y_front + 1.0), z) for b, z in zip(back, zs)] + [(y_front, z_low)]
    slopes = [steep] + [steep if clipped[k] or clipped[k + 1] else saucer
                        for k in range(len(zs) - 1)] + [saucer]
    if z_low < z_c:
        poly.append((y_front, z_c))
        slopes.append(steep)
        for pt in arc[1:]:
            poly.append(pt)
            slopes.append(steep)
    slopes.append(steep)                                # back up to the first vertex
    return np.array(poly, float), np.array(slopes, float)


def _segment_distance(pa, pb, a0, b0, a1, b1):
    """Distance [mm] from points (pa, pb) to the segment (a0, b0)-(a1, b1)."""
    da, db = a1 - a0, b1 - b0
    n2 = da * da + db * db
    t = np.clip(((pa - a0) * da + (pb - b0) * db) / n2, 0.0, 1.0) if n2 > 0 else 0.0
    return np.hypot(pa - (a0 + t * da), pb - (b0 + t * db))


def _cortex_x(lm, y, z):
    """Case-frame x [mm] of the cortex at (y, z) (median height within 2 mm)."""
    cx = lm.cortex
    height, h = cx["height"], cx["h"]
    ys = cx["y0"] + h * np.arange(height.shape[0])
    zs = cx["z0"] + h * np.arange(height.shape[1])
    lat = 1.0 if lm.side == "left" else -1.0
    out = []
    for yy, zz in zip(np.atleast_1d(y), np.atleast_1d(z)):
        j = np.abs(ys - yy) <= 2.0
        k = np.abs(zs - zz) <= 2.0
        vals = height[np.ix_(j, k)]
        vals = vals[np.isfinite(vals)]
        out.append(lat * (np.median(vals) if vals.size else np.nanmax(height)))
    return np.array(out)


# ------------------------------------------------------------------ strokes
def strokes(mask: np.ndarray, step_cells: float, _depth: int = 0) -> list[np.ndarray]:
    """Contour-parallel strokes over a region of lattice cells.

    Parameters
    ----------
    mask : (na, nb) bool
        The region.
    step_cells : float
        Spacing of the strokes [cells].

    Returns
    -------
    list of (m, 2) int
        Lattice indices along each stroke, outermost first: the cells on the
        contour lines of the distance to the region's edge at ``(k + 1/2)
        step`` (the middle line alone when the region is narrower), each a
        sequence of neighbouring cells of the region (consecutive duplicates
        removed; a closed contour ends where it starts). Cells that no level
        reaches within a spacing (a narrow arm) get strokes of their own, after
        the rest.
    """
    from scipy import ndimage
    from skimage.measure import find_contours

    mask = np.asarray(mask, bool)
    if not mask.any():
        return []
    edt = ndimage.distance_transform_edt(np.pad(mask, 1))
    top = float(edt.max())
    levels = [(k + 0.5) * step_cells for k in range(int(top / step_cells + 0.5) + 1)
              if (k + 0.5) * step_cells < top]
    if not levels:
        levels = [0.5 * (top + 1.0)] if top > 1.0 else [0.5]
    out = []
    for lev in levels:
        for c in find_contours(edt, lev):
            seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
            length = float(seg.sum())
            n = max(2, int(math.ceil(length / 0.5)) + 1)
            t = np.concatenate([[0.0], np.cumsum(seg)])
            pts = np.stack([np.interp(np.linspace(0, length, n), t, c[:, i])
                            for i in range(2)], axis=1)
            idx = np.rint(pts).astype(int) - 1                 # undo the pad
            ok = np.all((idx >= 0) & (idx < mask.shape), axis=1)
            idx = idx[ok]
            idx = idx[mask[idx[:, 0], idx[:, 1]]] if len(idx) else idx
            if len(idx) == 0:
                continue
            keep = np.ones(len(idx), bool)
            keep[1:] = np.any(idx[1:] != idx[:-1], axis=1)
            out.append(idx[keep])
    if not out:                                  # a sliver: its cells in order
        out.append(np.argwhere(mask))
    # a lobe thinner than the outer level (a narrow arm of the region) holds no
    # contour at the region's levels: its cells, farther than a spacing from
    # every stroke, get strokes of their own (the middle line of a thin lobe)
    if _depth < 8:
        hit = np.zeros(mask.shape, bool)
        cells = np.concatenate(out)
        hit[cells[:, 0], cells[:, 1]] = True
        far = mask & (ndimage.distance_transform_edt(~hit) > step_cells)
        lab, n = ndimage.label(far)
        for k in range(1, n + 1):
            out.extend(strokes(lab == k, step_cells, _depth=_depth + 1))
    return out


def _rotate_to(stroke: np.ndarray, start: int) -> np.ndarray:
    """A closed stroke started at ``start`` (an open one is only reversed
    when ``start`` is nearer its end)."""
    closed = len(stroke) > 2 and np.abs(stroke[0] - stroke[-1]).max() <= 1
    if closed:
        return np.concatenate([stroke[start:], stroke[:start]])
    return stroke[::-1] if start > len(stroke) // 2 else stroke


# ------------------------------------------------------------------- planning
def mastoidectomy_path(labels, spacing_mm, origin_mm, structures, lm, eye_mm, focal_mm,
                       plan, clearance, two_burrs: bool = True,
                       until_s: float | None = None):
    """Plan the mastoidectomy (see the module docstring).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel of the engine's grid (``s >= 1`` is
        ``structures[s - 1]``).
    spacing_mm : float
        Grid voxel edge [mm].
    origin_mm : (3,) float
        Centre of grid voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``name``, ``kind`` (and ``anatomy``).
    lm : bonesim.io.landmarks.Landmarks
        The case's landmarks (:data:`NEEDED` among them).
    eye_mm, focal_mm : (3,) float
        The case camera; the approach runs from the eye toward the focal point.
    plan : DemoPlan
        With the burrs' radii and speeds.
    clearance : Clearance
        Distances to every structure that is not bone, at source resolution.
    two_burrs : bool
        The finishing stage uses burr 1 (else burr 0).
    until_s : float, optional
        Stop planning once the path lasts longer than this [s] and return the
        samples at times up to it: the same samples, to the bit, as the whole
        plan's up to that time (waypoints are added in time order and every
        decision about one uses only what came before it; the samples are
        linear between waypoints). The summary then describes the part
        planned and says ``"until_s"``. For runs that use only a plan's
        start (synthetic cohorts of runs of a few seconds).

    Returns
    -------
    trajectory : Trajectory
    summary : dict
    """
    from skimage.draw import polygon2mask

    from bonesim.physics.clearance import Clearance

    labels = np.asarray(labels)
    origin = np.asarray(origin_mm, float)
    spacing = float(spacing_mm)
    kinds = np.array(["none"] + [s.kind for s in structures])
    is_bone = (kinds == "bone")[labels]
    if not is_bone.any():
        raise BonesimError("the case has no bone to drill")
    crit, thin, canal_ids = danger_groups(structures)
    held = set(clearance.structures)
    lacking = sorted(set(crit + thin + canal_ids) - held)
    if lacking:
        raise ValueError(f"the clearance field lacks structure(s) {lacking}")
    sets = [(g, key) for g, key in ((crit, "critical"), (thin, "thin"),
                                    (canal_ids, "canal")) if g]
    gmask = clearance.group_mask([g for g, _ in sets])
    lat = 1.0 if lm.side == "left" else -1.0

    # -- bone within edge_mm of the volume's faces: never drilled
    kinds_list = [s.kind for s in structures]
    coarse, hc, oc = analysis_grid(labels, spacing, origin, kinds_list,
                                   max(spacing, 0.5))
    lo_mm = origin - spacing / 2
    hi_mm = origin + spacing * (np.array(labels.shape) - 0.5)
    band = np.zeros(coarse.shape, bool)
    w = int(math.ceil((plan.edge_mm + spacing) / hc))
    for a in range(3):
        idx = [slice(None)] * 3
        idx[a] = slice(0, w)
        band[tuple(idx)] = True
        idx[a] = slice(coarse.shape[a] - w, coarse.shape[a])
        band[tuple(idx)] = True
    band &= coarse > 0
    edge = Clearance(band.astype(np.uint8), hc, oc, [1]) if band.any() else None

    # -- the ear canal where it is not labelled: a capsule along it
    canal_lm = lm.get("ear_canal")
    capsule = None
    if not canal_ids and canal_lm.confidence != "labelled":
        c0 = np.asarray(canal_lm.point_mm, float)
        lateral = np.array([lat, 0.0, 0.0])
        capsule = (c0 + 10.0 * lateral, c0 - 25.0 * lateral,
                   float(canal_lm.detail["radius_mm"]))

    def capsule_dist(p):
        a, b, r = capsule
        ab = b - a
        t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
        off = p - (a + t[:, None] * ab)
        return np.sqrt(np.einsum("ij,ij->i", off, off)) - r

    def gap_for(radius, m_crit, m_thin, m_canal):
        need = {"critical": m_crit, "thin": m_thin, "canal": m_canal}
        c = np.array([radius + need[key] for _, key in sets])

        def gap(p):
            p = np.asarray(p, float).reshape(-1, 3)
            out = (clearance.distances(p, gmask) - c).min(axis=1) if len(c) else \
                np.full(len(p), np.inf)
            if edge is not None:
                out = np.minimum(out, edge.distance(p) - radius)
            if capsule is not None:
                out = np.minimum(out, capsule_dist(p) - (radius + m_canal))
            return out
        return gap

    r1, r2 = plan.burr_radius_mm, plan.finish_radius_mm
    gap1 = gap_for(r1, plan.bulk_margin_mm, plan.bulk_thin_mm, plan.bulk_canal_mm)
    gap2 = gap_for(r2, plan.margin_mm, plan.thin_margin_mm, plan.canal_margin_mm)
    # travel and rinse moves keep the bigger burr's bulk margins
    gap_travel = gap1

    # -- the view and the lattice of columns over the outline
    eye = np.asarray(eye_mm, float)
    view = np.asarray(focal_mm, float) - eye
    if not np.linalg.norm(view) > 0:
        raise BonesimError("camera eye and focal point coincide")
    view /= np.linalg.norm(view)
    u, v = view_frame(view)

    def at(a, b, d):
        return eye + np.multiply.outer(a, u) + np.multiply.outer(b, v) \
            + np.multiply.outer(d, view)

    poly_yz, slopes = _outline_yz(lm, plan, lo_mm, hi_mm)
    poly3 = np.column_stack([_cortex_x(lm, poly_yz[:, 0], poly_yz[:, 1]), poly_yz])
    pa, pb = (poly3 - eye) @ u, (poly3 - eye) @ v
    g = plan.column_mm
    pad = r1 + 2.0
    a0, b0 = pa.min() - pad, pb.min() - pad
    na = int(math.ceil((pa.max() + pad - a0) / g)) + 1
    nb = int(math.ceil((pb.max() + pad - b0) / g)) + 1
    inside = polygon2mask((na, nb), np.column_stack([(pa - a0) / g, (pb - b0) / g]))
    focal = np.asarray(focal_mm, float)
    if plan.region_radius_mm > 0:
        fa, fb = (focal - eye) @ u, (focal - eye) @ v
        ia, ib = np.meshgrid(a0 + g * np.arange(na), b0 + g * np.arange(nb), indexing="ij")
        inside &= (ia - fa) ** 2 + (ib - fb) ** 2 <= plan.region_radius_mm ** 2
    if not inside.any():
        raise BonesimError("the cavity's outline covers no column of the view")
    cols = np.argwhere(inside)
    ca, cb = a0 + g * cols[:, 0], b0 + g * cols[:, 1]
    # the saucer: per edge, the deepest cut surface below entry at distance
    # x from it is slope x; a burr touches that wall with its centre
    # r sqrt(1 + slope^2) above it
    n_edges = len(pa)
    wall_terms = []
    for k in range(n_edges):
        d = _segment_distance(ca, cb, pa[k], pb[k], pa[(k + 1) % n_edges],
                              pb[(k + 1) % n_edges])
        wall_terms.append((slopes[k], d))
    base = at(ca, cb, 0.0)
    shape = np.array(labels.shape)
    corners = origin + spacing * (np.array(list(np.ndindex(2, 2, 2))) * (shape - 1))
    reach = np.linalg.norm(corners - eye, axis=1).max() + r1
    depth = np.arange(0.0, reach, spacing / 2)
    entry = first_bone(is_bone, origin, spacing, base, view, depth)
    floor1 = trace_floors(gap1, base, view, 0.0, reach)
    floor2 = trace_floors(gap2, base, view, 0.0, reach)
    ant = lm.point("antrum")
    t_ant = float((ant - eye) @ view) + plan.below_antrum_mm

    def wall_bound(r):
        """Deepest burr centre the saucer's walls allow per column [mm]: a
        sphere touching a wall of slope ``s`` (depth per mm inward) has its
        centre ``r sqrt(1 + s^2)`` above it; a vertical wall (``s`` inf,
        parallel to the view) only keeps centres ``r`` inside the edge."""
        out = np.full(len(cols), np.inf)
        for slope, d in wall_terms:
            if math.isinf(slope):
                out = np.where(d >= r, out, -np.inf)
            else:
                out = np.minimum(out, entry + slope * d - r * math.sqrt(1.0 + slope ** 2))
        return out

    def target(floor, r):
        t = np.minimum(np.minimum(floor, wall_bound(r)), t_ant)
        return np.where(np.isfinite(entry) & (t > entry - r), t, -np.inf)

    t1 = target(floor1, r1)
    t2 = target(floor2, r2)
    if not np.isfinite(t1).any() and not np.isfinite(t2).any():
        raise BonesimError("no bone inside the cavity's outline can be drilled with "
                           "its margins kept (the structures lie too close under the "
                           "cortex)")
    reachable = np.isfinite(entry)
    top = float(entry[reachable].min())
    # travel plane: clear over the whole lattice box, above the most lateral bone
    ga, gb = np.meshgrid(a0 + g * np.arange(0, na, 2), b0 + g * np.arange(0, nb, 2),
                         indexing="ij")
    lift = travel_height(gap_travel, at, ga.ravel(), gb.ravel(), top - r1 - TRAVEL_ABOVE_MM)

    def across_for(gap):
        def across(base0, base1, d):
            while d > lift and not segment_clear(gap, base0 + d * view, base1 + d * view,
                                                 0.0):
                d = max(d - STAIR_RAISE_MM, lift)
            return d
        return across

    # the burrs' swept spheres: shrunk, for the rinses (what surely went), and
    # whole, for where the finishing burr starts (what the cutting burr reached)
    swept = CutSurface(is_bone, origin, spacing, eye, u, v, view, depth, ca, cb, r1, 0.0,
                       0.0)
    surface = CutSurface(is_bone, origin, spacing, eye, u, v, view, depth, ca, cb, r1,
                         plan.uncut_mm, plan.rinse_gap_mm)
    path = PathBuilder(at(float(ca.mean()), float(cb.mean()), lift), until_s,
                       2.0 / plan.sample_hz)
    index = -np.ones((na, nb), int)
    index[cols[:, 0], cols[:, 1]] = np.arange(len(cols))
    reached = np.full(len(cols), -np.inf)
    drilled_at_rinse = [0.0]
    summary = {"columns": int(len(cols)), "outline_yz_mm": np.round(poly_yz, 2).tolist(),
               "stages": []}

    # rinse lines: every stroke spacing of the cutting burr across the lattice
    every = max(1, int(round(2.0 * r1 * (1.0 - plan.line_overlap) / g)))
    rinse_cols = np.flatnonzero(cols[:, 0] % every == 0)

    def do_rinse():
        rc = rinse_cols
        rinse(path, surface, ca[rc], cb[rc], reached[rc], floor1[rc], lift, at, view,
              gap_travel, plan)
        drilled_at_rinse[0] = path.drill_s

    def run_stage(tgt, floor, r, start, layer_mm, speed, gap, burr_index, relative):
        """Passes ``layer_mm`` apart down to ``tgt``: planes across the view
        from the shallowest start, or (``relative``) shells following each
        column's ``start`` (the cut so far)."""
        across = across_for(gap)
        step = max(2.0 * r * (1.0 - plan.line_overlap), g) / g
        prev = start.copy()
        n_strokes = 0
        top_now = np.maximum(start, entry - r)
        d_layer = 0.0 if relative else float(np.min(np.where(np.isfinite(tgt), top_now,
                                                             np.inf)))
        first = True
        for _ in range(plan.n_layers):
            d_layer += layer_mm
            now = np.minimum(top_now + d_layer if relative else d_layer, tgt)
            cuts = np.isfinite(tgt) & (now > prev + 1e-9) & (now > entry - r)
            if not cuts.any():
                if np.all(~np.isfinite(tgt) | (tgt <= prev + 1e-9)):
                    break
                continue
            region = np.zeros((na, nb), bool)
            region[cols[cuts, 0], cols[cuts, 1]] = True
            for stroke in strokes(region, step):
                q = index[stroke[:, 0], stroke[:, 1]]
                start_at = int(np.argmax(floor[q] - now[q]))
                stroke = _rotate_to(stroke, start_at)
                q = index[stroke[:, 0], stroke[:, 1]]
                b_first = at(ca[q[0]], cb[q[0]], 0.0)
                last = path.last
                d_last = float((last - eye) @ view)
                base_last = last - d_last * view
                if first or np.linalg.norm(base_last - b_first) > _FAR_STROKES * step * g:
                    path.go(base_last + lift * view, plan.travel_mm_s, drill=not first)
                    if first:                      # the burr changes with the drill off
                        path.burr = burr_index
                    path.go(b_first + lift * view, plan.travel_mm_s, drill=not first)
                    opened = max(prev[q[0]], lift)
                    if opened < now[q[0]]:
                        path.go(b_first + opened * view, plan.travel_mm_s, drill=True)
                    path.go(b_first + now[q[0]] * view, plan.plunge_mm_s, drill=True)
                    first = False
                else:
                    stair(path, base_last, b_first, view, d_last, now[q[0]], speed, across,
                          drill=True)
                stairs_along(path, at(ca[q], cb[q], 0.0), now[q], view, speed, gap, lift,
                             drill=True)
                surface.carve(ca[q], cb[q], now[q], r)
                swept.carve(ca[q], cb[q], now[q], r)
                n_strokes += 1
            reached[cuts] = np.maximum(reached[cuts], now[cuts] + r - r1)
            prev = np.where(cuts, now, prev)
            if path.drill_s - drilled_at_rinse[0] >= plan.rinse_every_s:
                path.go(path.last - (float((path.last - eye) @ view) - lift) * view,
                        plan.travel_mm_s)
                do_rinse()
                first = True
        return prev, n_strokes

    try:
        # -- stage 1: the bulk with the cutting burr
        t_before = path.drill_s
        done1, n1 = run_stage(t1, floor1, r1, np.full(len(cols), -np.inf), plan.layer_mm,
                              plan.speed_mm_s, gap1, 0, False)
        cut1 = swept.carved.copy()           # the cut surface the cutting burr left
        summary["stages"].append({"burr": 0, "strokes": n1, "drilling_s": round(
            path.drill_s - t_before, 1)})
        # -- stage 2: thin near the structures, finish the cavity: the columns
        # where the structures, not the saucer's wall or the antrum's depth, set
        # how deep the cutting burr went, and the finishing burr goes deeper
        near = floor1 <= np.minimum(wall_bound(r1), t_ant) + 1e-6
        _debug.update(base=base, entry=entry, floor1=floor1, floor2=floor2, t1=t1, t2=t2,
                      wall2=wall_bound(r2), wall1=wall_bound(r1), t_ant=t_ant, cut1=cut1,
                      near=near)
        # per column: how much deeper the finishing burr's bottom goes than the
        # cutting burr's did there (where the cutting burr's centre never went,
        # than the cortex): along the walls this is what it thins sideways
        bottom1 = np.where(np.isfinite(t1), t1 + r1, entry)
        gain = np.where(np.isfinite(t2), t2 + r2 - bottom1, -np.inf)
        t2f = np.where(near & (gain >= plan.finish_gain_mm), t2, -np.inf)
        if np.isfinite(t2f).any():
            path.go(path.last - (float((path.last - eye) @ view) - lift) * view,
                    plan.travel_mm_s)
            start2 = bottom1 - r2
            t_before = path.drill_s
            done2, n2 = run_stage(t2f, floor2, r2, start2, plan.finish_layer_mm,
                                  plan.finish_speed_mm_s, gap2, 1 if two_burrs else 0, True)
            summary["stages"].append({"burr": 1 if two_burrs else 0, "strokes": n2,
                                      "drilling_s": round(path.drill_s - t_before, 1),
                                      "columns": int(np.isfinite(t2f).sum())})
        path.go(path.last - (float((path.last - eye) @ view) - lift) * view, plan.travel_mm_s)
        if path.drill_s > drilled_at_rinse[0]:
            do_rinse()
    except PathLongEnough:                  # planned past until_s: enough
        summary["until_s"] = float(until_s)

    t, pos, state, burr = path.sampled(plan.sample_hz)
    if until_s is not None:                 # the samples up to until_s
        k = int(np.searchsorted(t, until_s, side="right"))
        t, pos, state, burr = t[:k], pos[:k], state[:k], burr[:k]
    n = len(t)
    rpm = np.where(burr == 1, plan.finish_rpm, plan.speed_rpm)
    summary.update({"duration_s": round(float(t[-1]), 1),
                    "drilling_s": round(path.drill_s, 1),
                    "antrum_depth_mm": round(t_ant, 2),
                    "deepest_cut_mm": round(float(np.max(np.where(np.isfinite(reached),
                                                                  reached + r1, -np.inf))
                                                  - top), 2)})
    traj = Trajectory(t_s=t, pos_mm=pos, axis=np.repeat(view[None, :], n, axis=0),
                      drill=state[:, 0], speed_rpm=rpm, direction=np.ones(n, dtype=np.int8),
                      suction=state[:, 1], irrigation=state[:, 2], burr=burr)
    return traj, summary
