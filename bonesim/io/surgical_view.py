"""The surgeon's lateral view of the mastoid, derived from the landmarks.

Frame
-----
Everything is in the case frame, LPS [mm] (``+x`` patient left, ``+y``
posterior, ``+z`` superior). For a left ear lateral is ``+x``, for a right
ear ``-x``; the *lateral coordinate* of a point is its distance along the
lateral direction.

How the view is chosen
----------------------
A mastoidectomy starts on the mastoid cortex behind and above the ear canal:
Macewen's (suprameatal) triangle, posterior-superior to the canal, in front of
the sigmoid sinus and below the tegmen, over the antrum. The landmarks come
from :func:`bonesim.io.landmarks.find_landmarks` (merged sinus-and-dura labels
split, the antrum found as an air space); parameters are in the ``[view]``
table of ``bonesim/data/anatomy.toml``:

1. **Focal point** ``(y_f, z_f)``: ``y_f`` halfway between the canal's
   posterior wall and the sinus's anterior edge (at least ``sinus_margin_mm``
   in front of the sinus), or ``posterior_mm`` behind the wall without a
   sinus; ``z_f`` a fraction ``tegmen_fraction`` of the way from the canal's
   axis up to the tegmen (at least ``tegmen_margin_mm`` below it). With no
   canal at all the focal point is the centroid of the bone's lateral face
   (columns within ``face_depth_mm`` of the most lateral bone). The focal
   point lies on the cortex: the median height over a disc of
   ``surface_radius_mm``.
2. **Direction**: along the cortex's outward normal there (a plane fitted over
   ``normal_radius_mm``), tilted at most ``max_tilt_deg`` from lateral and
   straight lateral when the normal is within ``snap_tilt_deg`` of it; the
   eye sits ``eye_distance_mm`` out along it, superior up.

Whether the anatomy agrees with the declared side and orientation is
:mod:`bonesim.io.anatomy_frame`'s question.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bonesim.io.anatomy import load_table
from bonesim.io.landmarks import Landmarks, find_landmarks

__all__ = ["SurgicalView", "surgical_view", "view_from_landmarks"]


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


def surgical_view(labels: np.ndarray, spacing_mm: float, origin_mm, structures,
                  side: str, params: dict | None = None) -> SurgicalView:
    """The surgeon's lateral view of the mastoid (see the module docstring).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s`` is ``structures[s - 1]``), axes x,
        y, z of the LPS case frame.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``name``, ``kind`` (bone is every ``"bone"``) and
        optionally ``anatomy``.
    side : {"left", "right"}
        The ear.
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
    p = dict(load_table().view)
    p.update(params or {})
    lm = find_landmarks(labels, spacing_mm, origin_mm, structures, side, view_params=p)
    return view_from_landmarks(lm, p)


def view_from_landmarks(lm: Landmarks, params: dict | None = None) -> SurgicalView:
    """The view from found landmarks and the cortex they were read on."""
    p = dict(load_table().view)
    p.update(params or {})
    lat = 1.0 if lm.side == "left" else -1.0
    cx = lm.cortex
    height = cx["height"]
    h = cx["h"]
    has = np.isfinite(height)
    if not has.any():
        raise ValueError("no bone in the volume: no surgical view")
    ys = cx["y0"] + h * np.arange(height.shape[0])
    zs = cx["z0"] + h * np.arange(height.shape[1])
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    notes = []
    marks: dict = {}
    canal = lm.get("ear_canal")
    if canal is not None:
        y_c, z_c = canal.point_mm[1], canal.point_mm[2]
        wall = canal.detail["posterior_wall_y_mm"]
        marks["canal"] = (float(y_c), float(z_c))
        sinus = lm.get("sigmoid_sinus")
        if sinus is not None:
            y_s = sinus.point_mm[1]
            marks["sinus_front"] = (float(y_s), float(sinus.point_mm[2]))
            y_f = min(0.5 * (wall + y_s), y_s - p["sinus_margin_mm"])
        else:
            y_f = wall + p["posterior_mm"]
            notes.append(f"no sinus: focal point {p['posterior_mm']:g} mm behind the "
                         "canal's posterior wall")
        teg = lm.get("tegmen")
        z_t = teg.point_mm[2]
        marks["tegmen"] = (float(teg.point_mm[1]), float(z_t))
        z_f = min(z_c + p["tegmen_fraction"] * (z_t - z_c), z_t - p["tegmen_margin_mm"])
    else:
        top = np.nanmax(height)
        face = has & (height >= top - p["face_depth_mm"])
        y_f, z_f = float(yy[face].mean()), float(zz[face].mean())
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
    focal = np.array([lat * s_f, float(y_f), float(z_f)])
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

