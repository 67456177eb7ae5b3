"""The surgeon's lateral view of the mastoid, derived from the anatomy, and
checks that a case's layout agrees with its declared side.

Frame
-----
Everything is in the case frame, LPS [mm] (``+x`` patient left, ``+y``
posterior, ``+z`` superior); arrays are indexed ``[i, j, k]`` along x, y, z.
For a left ear lateral is ``+x``, for a right ear ``-x``. Below, the *lateral
coordinate* of a point is its distance along the lateral direction
(``x`` for a left ear, ``-x`` for a right one).

How the view is chosen
----------------------
A mastoidectomy starts on the mastoid cortex behind and above the ear canal:
Macewen's (suprameatal) triangle, posterior-superior to the canal, in front of
the sigmoid sinus and below the tegmen, over the antrum. The view is built from
landmarks read in the loaded volume (structures are recognised by name, see
:mod:`bonesim.io.anatomy`; parameters in the ``[view]`` table of
``bonesim/data/anatomy.toml``):

1. **Lateral bone surface.** For every ``(y, z)`` column the most lateral
   bone voxel gives a height map of the cortex as seen from the side.
2. **Ear canal** (its axis ``y_c, z_c`` and radius ``r_c``), first found of:
   a structure read as the ear canal; else the canal opening seen as an air
   channel through the lateral cortex (a pit in the height map deeper than
   ``pit_depth_mm`` below its closed surroundings, of canal-like area; the
   one nearest the middle ear when ossicles or a middle ear are labelled);
   else the middle ear (ossicles, tympanic membrane, middle-ear air) projected
   laterally, radius ``canal_radius_mm``.
3. **Sigmoid sinus**: its anterior edge ``y_s`` near the canal's height;
   **tegmen**: the lowest middle-fossa dura ``z_t`` above the canal.
4. **Focal point** ``(y_f, z_f)``: ``y_f`` halfway between the canal's
   posterior wall ``y_c + r_c`` and ``y_s`` (at least ``sinus_margin_mm``
   in front of the sinus), or ``posterior_mm`` behind the wall without a
   sinus; ``z_f`` a fraction ``tegmen_fraction`` of the way from ``z_c`` up
   to ``z_t`` (at least ``tegmen_margin_mm`` below it), or ``superior_mm``
   above ``z_c`` without a tegmen. With no canal at all the focal point is
   the centroid of the bone's lateral face (columns within ``face_depth_mm``
   of the most lateral bone), kept in front of the sinus and below the
   tegmen when those are known. The focal point lies on the cortex: the
   median height over a disc of ``surface_radius_mm``.
5. **Direction**: along the cortex's outward normal there (a plane fitted over
   ``normal_radius_mm``), tilted at most ``max_tilt_deg`` from lateral and
   straight lateral when the normal is within ``snap_tilt_deg`` of it; the
   eye sits ``eye_distance_mm`` out along it, superior up.

:func:`side_warnings` compares the structures' positions with the declared
side and the frame (sinus behind the canal, labyrinth medial to the middle
ear, middle-fossa dura above the labyrinth, mastoid bone lateral to the
sinus) and says what looks mirrored.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from bonesim.io.anatomy import load_table

__all__ = ["SurgicalView", "surgical_view", "lateral_height_map", "find_canal_pits",
           "side_warnings"]

_SIDES = ("left", "right")


@dataclass(frozen=True)
class SurgicalView:
    """A derived camera and how it was found.

    Attributes
    ----------
    eye_mm, focal_mm : (3,) float
        Eye and focal point in the case frame [mm]; the focal point lies on
        the mastoid cortex.
    up : (3,) float
        Unit up vector, perpendicular to the view (superior up).
    landmarks : dict of str -> tuple of float
        Landmarks used [mm]: ``canal`` (the canal's axis), ``sinus_front``
        (the sinus's anterior edge) and ``tegmen`` (its lowest point) as
        ``(y, z)``; ``focal`` as ``(x, y, z)``.
    notes : tuple of str
        One line per decision, for ``bonesim case-info``.
    """

    eye_mm: tuple
    focal_mm: tuple
    up: tuple
    landmarks: dict
    notes: tuple


def _check(labels, spacing_mm, origin_mm, side):
    labels = np.asarray(labels)
    if labels.ndim != 3:
        raise ValueError(f"labels must be 3-D, got shape {labels.shape}")
    if side not in _SIDES:
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    if not float(spacing_mm) > 0:
        raise ValueError("spacing_mm must be positive")
    return labels, float(spacing_mm), np.asarray(origin_mm, float).reshape(3), \
        (1.0 if side == "left" else -1.0)


def lateral_height_map(mask: np.ndarray, spacing_mm: float, origin_mm, side: str
                       ) -> np.ndarray:
    """Lateral coordinate of the most lateral voxel of ``mask`` per column.

    Parameters
    ----------
    mask : (nx, ny, nz) bool
        Axes x, y, z.
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    side : {"left", "right"}
        Lateral is ``+x`` for a left ear, ``-x`` for a right one.

    Returns
    -------
    (ny, nz) float64
        ``x`` (left) or ``-x`` (right) of that voxel's centre [mm]; NaN where
        the column holds no voxel of ``mask``.
    """
    mask, h, origin, lat = _check(mask, spacing_mm, origin_mm, side)
    mask = mask.astype(bool, copy=False)
    nx = mask.shape[0]
    has = mask.any(axis=0)
    if lat > 0:
        i = nx - 1 - np.argmax(mask[::-1], axis=0)
    else:
        i = np.argmax(mask, axis=0)
    out = lat * (origin[0] + h * i)
    out[~has] = np.nan
    return out


def find_canal_pits(height: np.ndarray, spacing_mm: float, closing_mm: float,
                    depth_mm: float, min_area_mm2: float, max_area_mm2: float,
                    rim_mm: float = 1.5, rim_fraction: float = 0.8) -> list[dict]:
    """Canal-like pits of a lateral height map (openings into the bone).

    A pit is a connected set of columns, inside the bone's silhouette (holes
    in it included), lying more than ``depth_mm`` below the map's grey
    closing with a ``(2 r + 1)``-column square, ``r = closing_mm / spacing``,
    and ringed by cortex: at least ``rim_fraction`` of the columns within
    ``rim_mm`` around it hold bone that is not itself in a pit (an opening
    in the cortex, not a notch at the bone's edge).

    Parameters
    ----------
    height : (ny, nz) float
        :func:`lateral_height_map` (NaN outside the bone) [mm].
    spacing_mm : float
        Column pitch [mm].
    closing_mm, depth_mm : float
        Closing half-width and least pit depth [mm].
    min_area_mm2, max_area_mm2 : float
        Accepted pit areas [mm^2].
    rim_mm, rim_fraction : float
        Width of the ring checked around a pit [mm] and the share of it that
        must be cortex.

    Returns
    -------
    list of dict
        ``j, k`` (column centroid, fractional indices), ``area_mm2``,
        ``depth_mm`` (mean depth below the closing), largest area first.
    """
    from scipy import ndimage

    height = np.asarray(height, dtype=float)
    has = np.isfinite(height)
    if not has.any():
        return []
    inside = ndimage.binary_fill_holes(has)
    floor = float(np.nanmin(height))
    h = np.where(has, height, floor)
    r = max(1, int(round(closing_mm / spacing_mm)))
    closed = ndimage.grey_closing(h, size=(2 * r + 1, 2 * r + 1), mode="nearest")
    depth = closed - h
    pit = inside & (depth > depth_mm)
    lab, n = ndimage.label(pit)
    out = []
    if n == 0:
        return out
    idx = np.arange(1, n + 1)
    counts = ndimage.sum_labels(np.ones_like(h), lab, idx)
    cents = ndimage.center_of_mass(np.ones_like(h), lab, idx)
    mean_depth = ndimage.mean(depth, lab, idx)
    cortex = has & ~(depth > depth_mm)
    ring_r = max(1, int(math.ceil(rim_mm / spacing_mm)))
    boxes = ndimage.find_objects(lab)
    for n_pit, (c, cen, d, box) in enumerate(zip(counts, cents, mean_depth, boxes), 1):
        area = float(c) * spacing_mm ** 2
        if not min_area_mm2 <= area <= max_area_mm2:
            continue
        lo = [max(b.start - ring_r, 0) for b in box]
        hi = [min(b.stop + ring_r, n) for b, n in zip(box, h.shape)]
        sub = lab[lo[0]:hi[0], lo[1]:hi[1]] == n_pit
        ring = ndimage.binary_dilation(sub, iterations=ring_r) & ~sub
        if (lo[0] == 0 or lo[1] == 0 or hi[0] == h.shape[0]
                           or hi[1] == h.shape[1]):
            continue                                  # runs off the map: no rim
        rim = cortex[lo[0]:hi[0], lo[1]:hi[1]][ring]
        if rim.size and rim.mean() >= rim_fraction:
            out.append({"j": float(cen[0]), "k": float(cen[1]), "area_mm2": area,
                        "depth_mm": float(d)})
    out.sort(key=lambda p: -p["area_mm2"])
    return out


def _role_voxels(labels, roles, role):
    idx = [s for s, r in enumerate(roles, start=1) if r == role]
    if not idx:
        return None
    ijk = np.argwhere(np.isin(labels, idx))
    return ijk if len(ijk) else None


def _names(names, roles, role):
    return ", ".join(repr(n) for n, r in zip(names, roles) if r == role)


def surgical_view(labels: np.ndarray, spacing_mm: float, origin_mm,
                  kinds: Sequence[str], roles: Sequence[str], side: str,
                  names: Sequence[str] | None = None, params: dict | None = None
                  ) -> SurgicalView:
    """The surgeon's lateral view of the mastoid (see the module docstring).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s`` is structure ``s - 1``), axes x, y, z
        of the LPS case frame.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    kinds : sequence of str
        Kind per structure; bone is every structure of kind ``"bone"``.
    roles : sequence of str
        Landmark role per structure (:data:`bonesim.io.anatomy.ROLES` or ``""``).
    side : {"left", "right"}
        The ear.
    names : sequence of str, optional
        Structure names, for the notes.
    params : dict, optional
        ``[view]`` parameters (default: the shipped anatomy table's).

    Returns
    -------
    SurgicalView

    Raises
    ------
    ValueError
        No bone in the volume, or inconsistent inputs.
    """
    labels, h, origin, lat = _check(labels, spacing_mm, origin_mm, side)
    n = len(kinds)
    if len(roles) != n:
        raise ValueError("kinds and roles must have one entry per structure")
    names = list(names) if names is not None else [f"#{s}" for s in range(1, n + 1)]
    p = dict(load_table().view)
    p.update(params or {})
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    bone = np.isin(labels, bone_idx)
    if not bone.any():
        raise ValueError("no bone in the volume: no surgical view")
    height = lateral_height_map(bone, h, origin, side)
    has = np.isfinite(height)
    ys = origin[1] + h * np.arange(labels.shape[1])
    zs = origin[2] + h * np.arange(labels.shape[2])
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    notes: list[str] = []
    marks: dict = {}

    def to_mm(ijk):
        return origin + h * np.asarray(ijk, float)

    def lat_point(y, z, s):
        return (lat * s, float(y), float(z))

    # -- middle ear reference (ossicles, tympanic membrane, middle-ear air)
    me = None
    for role in ("ossicles", "middle_ear"):
        v = _role_voxels(labels, roles, role)
        if v is not None:
            me = (to_mm(v.mean(axis=0)), _names(names, roles, role))
            break

    # -- ear canal
    canal = None                      # (y, z, radius, how)
    v = _role_voxels(labels, roles, "ear_canal")
    if v is not None:
        pts = to_mm(v)
        y5, y95 = np.percentile(pts[:, 1], [5, 95])
        z5, z95 = np.percentile(pts[:, 2], [5, 95])
        r = float(np.clip(0.25 * ((y95 - y5) + (z95 - z5)) + h / 2, 1.0, 10.0))
        c = pts.mean(axis=0)
        canal = (c[1], c[2], r, f"ear canal: the labelled {_names(names, roles, 'ear_canal')}")
    if canal is None:
        pits = find_canal_pits(height, h, p["pit_closing_mm"], p["pit_depth_mm"],
                               p["pit_min_area_mm2"], p["pit_max_area_mm2"],
                               p["pit_rim_mm"], p["pit_rim_fraction"])
        if pits:
            if me is not None:
                ref = me[0]
                pits.sort(key=lambda q: math.hypot(ys[0] + h * q["j"] - ref[1],
                                                   zs[0] + h * q["k"] - ref[2]))
            q = pits[0]
            y, z = ys[0] + h * q["j"], zs[0] + h * q["k"]
            r = math.sqrt(q["area_mm2"] / math.pi)
            canal = (y, z, r, "ear canal: the air channel through the lateral cortex "
                     f"(opening {q['area_mm2']:.0f} mm^2, {q['depth_mm']:.0f} mm deep)")
    if canal is None and me is not None:
        canal = (me[0][1], me[0][2], p["canal_radius_mm"],
                 f"ear canal: lateral to the middle ear ({me[1]}), no canal seen")
    if canal is not None:
        y_c, z_c, r_c, how = canal
        notes.append(f"{how}; axis at y {y_c:.1f}, z {z_c:.1f} mm, radius {r_c:.1f} mm")
        marks["canal"] = (float(y_c), float(z_c))

    # -- sinus front and tegmen near the canal's height
    y_s = z_t = None
    v = _role_voxels(labels, roles, "sinus")
    if v is not None:
        pts = to_mm(v)
        if canal is not None:
            band = pts[np.abs(pts[:, 2] - z_c) <= p["band_mm"]]
            pts = band if len(band) else pts
        y_s = float(np.percentile(pts[:, 1], 5))
        if canal is not None and y_s <= y_c + r_c:
            notes.append(f"sinus ({_names(names, roles, 'sinus')}) lies in front of the "
                         "canal's posterior wall: not used")
            y_s = None
        else:
            notes.append(f"sigmoid sinus: {_names(names, roles, 'sinus')}, anterior edge "
                         f"at y {y_s:.1f} mm")
            marks["sinus_front"] = (y_s, float(np.median(pts[:, 2])))
    v = _role_voxels(labels, roles, "tegmen")
    if v is not None:
        pts = to_mm(v)
        if canal is not None:
            near = pts[(np.abs(pts[:, 1] - y_c) <= 2 * p["band_mm"]) & (pts[:, 2] > z_c)]
            pts = near if len(near) else pts
        z_t = float(np.percentile(pts[:, 2], 5))
        if canal is not None and z_t <= z_c:
            notes.append(f"tegmen ({_names(names, roles, 'tegmen')}) lies below the "
                         "canal: not used")
            z_t = None
        else:
            notes.append(f"tegmen: {_names(names, roles, 'tegmen')}, lowest at "
                         f"z {z_t:.1f} mm")
            marks["tegmen"] = (float(np.median(pts[:, 1])), z_t)

    # -- focal point in (y, z)
    if canal is not None:
        wall = y_c + r_c
        if y_s is not None:
            y_f = min(0.5 * (wall + y_s), y_s - p["sinus_margin_mm"])
        else:
            y_f = wall + p["posterior_mm"]
            notes.append(f"no sinus: focal point {p['posterior_mm']:g} mm behind the "
                         "canal's posterior wall")
        if z_t is not None:
            z_f = min(z_c + p["tegmen_fraction"] * (z_t - z_c), z_t - p["tegmen_margin_mm"])
        else:
            z_f = z_c + p["superior_mm"]
            notes.append(f"no tegmen: focal point {p['superior_mm']:g} mm above the "
                         "canal's axis")
    else:
        top = np.nanmax(height)
        face = has & (height >= top - p["face_depth_mm"])
        y_f, z_f = float(yy[face].mean()), float(zz[face].mean())
        if y_s is not None:
            y_f = min(y_f, y_s - p["sinus_margin_mm"])
        if z_t is not None:
            z_f = min(z_f, z_t - p["tegmen_margin_mm"])
        notes.append("no ear canal found: focal point on the centre of the bone's "
                     "lateral face")

    # -- focal on the cortex, direction along its normal
    d2 = (yy - y_f) ** 2 + (zz - z_f) ** 2
    disc = has & (d2 <= p["surface_radius_mm"] ** 2)
    if not disc.any():
        jk = np.unravel_index(np.argmin(np.where(has, d2, np.inf)), d2.shape)
        disc = np.zeros_like(has)
        disc[jk] = True
        notes.append("no bone right under the focal point: the nearest bone's "
                     "height is used")
    s_f = float(np.median(height[disc]))
    focal = np.array(lat_point(y_f, z_f, s_f))
    wide = has & (d2 <= p["normal_radius_mm"] ** 2)
    lateral = np.array([lat, 0.0, 0.0])
    normal = lateral.copy()
    if wide.sum() >= 3:
        a = np.c_[np.ones(wide.sum()), yy[wide] - y_f, zz[wide] - z_f]
        coef, *_ = np.linalg.lstsq(a, height[wide], rcond=None)
        normal = np.array([lat, -coef[1], -coef[2]])
        normal /= np.linalg.norm(normal)
    tilt = math.degrees(math.acos(float(np.clip(normal @ lateral, -1.0, 1.0))))
    limit = p["max_tilt_deg"]
    if tilt < p["snap_tilt_deg"]:
        normal, tilt = lateral, 0.0                   # a dome's slope, not a face
    elif tilt > limit:
        perp = normal - (normal @ lateral) * lateral
        perp /= np.linalg.norm(perp)
        normal = math.cos(math.radians(limit)) * lateral + \
            math.sin(math.radians(limit)) * perp
        notes.append(f"cortex normal {tilt:.0f} deg from lateral: view tilted "
                     f"{limit:g} deg only")
        tilt = limit
    view = -normal
    up = np.array([0.0, 0.0, 1.0]) - view[2] * view
    up /= np.linalg.norm(up)
    eye = focal + p["eye_distance_mm"] * normal
    notes.append(f"focal point on the mastoid cortex at {np.round(focal, 1).tolist()} mm,"
                 f" view {tilt:.0f} deg from lateral, superior up")
    marks["focal"] = tuple(float(c) for c in focal)
    return SurgicalView(tuple(float(c) for c in eye), tuple(float(c) for c in focal),
                        tuple(float(c) for c in up), marks, tuple(notes))


# ------------------------------------------------------------------ checks
def _centroids(labels, n):
    from scipy import ndimage

    idx = np.arange(1, n + 1)
    counts = np.bincount(labels.ravel(), minlength=n + 1)[1:n + 1]
    cents = np.array(ndimage.center_of_mass(np.ones(labels.shape, np.uint8), labels, idx)
                     if n else np.zeros((0, 3)), dtype=float).reshape(-1, 3)
    return counts, cents


def side_warnings(labels: np.ndarray, spacing_mm: float, origin_mm,
                  kinds: Sequence[str], roles: Sequence[str], side: str,
                  names: Sequence[str] | None = None, lateral_mm: float = 15.0
                  ) -> list[str]:
    """Where the structures' layout contradicts the declared side and frame.

    Checks, each when both structures are present (centroids of all
    structures of a role): the sigmoid sinus lies posterior to the ear canal
    (else the middle ear); the labyrinth lies medial to the middle ear and to
    the canal; the middle-fossa dura (tegmen) lies above the labyrinth (else
    the middle ear); there is more bone within ``lateral_mm`` lateral of the
    sinus (the mastoid) than medial of it (the posterior fossa).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure indices, axes x, y, z of the LPS case frame.
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    kinds, roles : sequence of str
        Kind and landmark role per structure.
    side : {"left", "right"}
        The declared ear.
    names : sequence of str, optional
        Structure names for the messages.
    lateral_mm : float
        Reach of the mastoid check [mm].

    Returns
    -------
    list of str
        One sentence per contradiction (empty when the layout agrees).
    """
    labels, h, origin, lat = _check(labels, spacing_mm, origin_mm, side)
    n = len(roles)
    names = list(names) if names is not None else [f"#{s}" for s in range(1, n + 1)]
    counts, cents = _centroids(labels, n)
    pos = {}
    for role in ("ear_canal", "ossicles", "middle_ear", "labyrinth", "sinus", "tegmen"):
        idx = [s for s in range(n) if roles[s] == role and counts[s] > 0]
        if idx:
            w = counts[idx].astype(float)
            c = origin + h * (cents[idx] * w[:, None]).sum(0) / w.sum()
            pos[role] = (c, ", ".join(repr(names[s]) for s in idx))
    if "ossicles" in pos:
        pos["middle ear"] = pos["ossicles"]
    elif "middle_ear" in pos:
        pos["middle ear"] = pos["middle_ear"]
    out = []
    lr = ("the stack looks mirrored left-right, or the ear is not the declared "
          f"{side}: check 'side' and the L/R letter of 'orientation'")
    ref = "ear_canal" if "ear_canal" in pos else "middle ear"
    if "sinus" in pos and ref in pos and pos["sinus"][0][1] < pos[ref][0][1]:
        out.append(f"the sigmoid sinus ({pos['sinus'][1]}) lies anterior to the "
                   f"{ref.replace('_', ' ')} ({pos[ref][1]}): the anterior/posterior "
                   "axis looks flipped (check the P/A letter of 'orientation')")
    for other in ("middle ear", "ear_canal"):
        if "labyrinth" in pos and other in pos and \
                lat * pos["labyrinth"][0][0] > lat * pos[other][0][0]:
            out.append(f"the labyrinth ({pos['labyrinth'][1]}) lies lateral to the "
                       f"{other.replace('_', ' ')} ({pos[other][1]}): {lr}")
    below = "labyrinth" if "labyrinth" in pos else "middle ear"
    if "tegmen" in pos and below in pos and pos["tegmen"][0][2] < pos[below][0][2]:
        out.append(f"the middle-fossa dura ({pos['tegmen'][1]}) lies below the "
                   f"{below} ({pos[below][1]}): the superior/inferior axis looks "
                   "flipped (check the S/I letter of 'orientation')")
    sinus = [s for s in range(n) if roles[s] == "sinus" and counts[s] > 0]
    bone_idx = [s + 1 for s in range(n) if kinds[s] == "bone"]
    if sinus and bone_idx:
        bone = np.isin(labels, bone_idx)
        ijk = np.argwhere(np.isin(labels, [s + 1 for s in sinus]))
        steps = np.arange(1, max(1, int(round(lateral_mm / h))) + 1)
        nx = labels.shape[0]

        def bone_along(sign):
            i = ijk[:, 0:1] + sign * steps[None, :]
            ok = (i >= 0) & (i < nx)
            hit = np.zeros(i.shape, bool)
            rows = np.broadcast_to(ijk[:, 1:2], i.shape)
            cols = np.broadcast_to(ijk[:, 2:3], i.shape)
            hit[ok] = bone[i[ok], rows[ok], cols[ok]]
            return hit.mean()

        outward = bone_along(int(lat))
        inward = bone_along(-int(lat))
        if inward > 1.5 * outward + 0.05:
            out.append(f"there is more bone medial to the sigmoid sinus "
                       f"({', '.join(repr(names[s]) for s in sinus)}) than lateral to "
                       f"it ({100 * inward:.0f} % vs {100 * outward:.0f} % within "
                       f"{lateral_mm:g} mm): the mastoid cortex faces medially; {lr}")
    return out
