"""The measurements behind the final-product assessment (:mod:`metrics.assessment`).

Everything is measured on the engine's voxel grid in a box around the drilled
voxels (``[measure] box_pad_mm`` of ``bonesim/data/assessment.toml``),
vectorised with numpy and scipy.ndimage; parameters are that table's.

Frame and arrays
----------------
Case frame, LPS [mm]; arrays indexed ``[i, j, k]`` along x, y, z; ``h`` the
voxel edge [mm]; a voxel's centre is ``origin + h * (i, j, k)``.

Definitions
-----------
Tissue
    ``tissue0``: voxels with a label and density at the start;
    ``present``: voxels with density at the end; ``removed = tissue0 &
    ~present`` (drilled, or cut off and shed).
Opened air
    Air at the start that lies inside the bone (tissue within ``hull_mm``
    along all six axis directions: the antrum and the air cells, not the ear
    canal or the outside), in 6-connected components that touch a removed
    voxel face to face, within ``opened_reach_mm`` of the removed voxels.
Cavity
    ``removed | opened air``.
Structure surface
    A structure's voxels with a face neighbour that was bone at the start
    (the part of it bone covered).
Cover [mm]
    Of a surface voxel: ``max(0, d - h)``, ``d`` the distance between its
    centre and the nearest cavity voxel's (exact Euclidean distance
    transform): the bone left between the structure and the cavity, as
    :mod:`metrics.exposure` with the opened air counted.
Exposed
    A surface voxel face to face with a removed voxel (distance at most
    ``h``): the run drilled its bone away. (Air that was already next to a
    structure and that the run opened does not expose it: that is the
    anatomy's, not the run's.)
Thinnest [mm]
    The least cover reached over at least ``min_area_mm2`` of a surface
    (surface voxels count ``h^2`` each): the ``ceil(min_area / h^2)``-th
    smallest cover; inf when the surface in the box is smaller.
Sight lines
    From the centre of each removed voxel face to face with remaining tissue
    (the cavity's surface) toward the eye, sampled every ``step_voxels * h``
    to the box's edge, nearest voxel. A sample hides it when it falls in an
    *occluder*: remaining tissue more than ``occluder_depth_voxels`` face
    steps from any removed voxel (the cavity's own skin is peeled off), so
    the voxel staircase of a wall seen edge-on never hides, while a rim over
    an undercut hides by its upper layers. The *hidden wall share* is the
    share of the cavity's wall (remaining voxels face to face with removed
    ones) none of whose removed neighbours sees the eye; the *overhang* is
    the remaining tissue hit by blocked sight lines, grown back over the
    peeled skin within the remaining tissue [mm^3].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from bonesim.io.landmarks import inside_hull

__all__ = ["FACES", "Box", "make_box", "face_adjacent", "opened_air",
           "thinnest", "cover_quantities", "sightlines", "antrum_quantities",
           "angle_gap", "reach_gap", "tip_gap", "injury_quantities", "surface_of"]

#: The six face-neighbour offsets.
FACES = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
#: Rays per chunk of the sight-line march.
_CHUNK = 2048


def _shift(a: np.ndarray, off) -> np.ndarray:
    """``out[v] = a[v + off]`` (False / 0 beyond the edge)."""
    out = np.zeros_like(a)
    src = tuple(slice(max(o, 0), a.shape[q] + min(o, 0)) for q, o in enumerate(off))
    dst = tuple(slice(max(-o, 0), a.shape[q] + min(-o, 0)) for q, o in enumerate(off))
    out[dst] = a[src]
    return out


def face_adjacent(mask: np.ndarray) -> np.ndarray:
    """Voxels with a face neighbour in ``mask`` (bool, same shape)."""
    m = np.asarray(mask, bool)
    out = np.zeros_like(m)
    for off in FACES:
        out |= _shift(m, off)
    return out


@dataclass
class Box:
    """The analysis box: the grid's voxels ``lo .. lo + shape - 1``.

    Attributes
    ----------
    lo : (3,) int
        First voxel in the grid.
    h : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of the box's voxel (0, 0, 0), case frame [mm].
    labels : (bx, by, bz) uint8
        Labels at the start.
    tissue0, present, removed, bone0 : (bx, by, bz) bool
    groups : dict of str -> (bx, by, bz) bool
        Structure groups (``sinus``, ``tegmen``, ``dura``, ``facial_nerve``,
        ``chorda_tympani``, ``labyrinth``, ``incus``, ``ear_canal`` (the
        lumen)), those the case has.
    cavity : (bx, by, bz) bool
    """

    lo: np.ndarray
    h: float
    origin_mm: np.ndarray
    labels: np.ndarray
    tissue0: np.ndarray
    present: np.ndarray
    removed: np.ndarray
    bone0: np.ndarray
    groups: dict = field(default_factory=dict)
    cavity: np.ndarray | None = None
    occluder: np.ndarray | None = None
    _dist: dict = field(default_factory=dict, repr=False)

    def centres(self, ijk) -> np.ndarray:
        """Case-frame centres [mm] of box voxels ``ijk`` (n, 3)."""
        return self.origin_mm + self.h * np.asarray(ijk, float)

    def index_of(self, p_mm) -> np.ndarray:
        """Nearest box voxel (int, may lie outside) of case-frame points (n, 3)."""
        return np.rint((np.asarray(p_mm, float).reshape(-1, 3) - self.origin_mm) /
                       self.h).astype(np.int64)

    def distance_to(self, key: str, mask: np.ndarray) -> np.ndarray:
        """Distance [mm] from every box voxel's centre to the nearest voxel of
        ``mask`` (inf everywhere when it is empty); cached under ``key``."""
        if key not in self._dist:
            m = np.asarray(mask, bool)
            self._dist[key] = ndimage.distance_transform_edt(~m, sampling=self.h) \
                if m.any() else np.full(m.shape, np.inf)
        return self._dist[key]


def make_box(labels0, present, h: float, origin_mm, pad_mm: float) -> tuple:
    """``(lo, hi)`` voxel bounds (hi exclusive) of the removed voxels' box
    grown by ``pad_mm``; None when nothing was removed."""
    removed = (np.asarray(labels0) > 0) & ~np.asarray(present, bool)
    if not removed.any():
        return None
    idx = np.argwhere(removed)
    pad = int(math.ceil(pad_mm / h)) + 1
    lo = np.maximum(idx.min(0) - pad, 0)
    hi = np.minimum(idx.max(0) + pad + 1, removed.shape)
    return lo, hi


def opened_air(box: Box, hull_mm: float, reach_mm: float, eye_mm=None,
               step_voxels: float = 0.5) -> np.ndarray:
    """Air the run opened (module docstring), box voxels, bool; with
    ``eye_mm``, only the part the eye sees (``box.occluder`` hides)."""
    air = ~box.tissue0
    inside = air & inside_hull(box.tissue0, int(round(hull_mm / box.h)))
    if not inside.any() or not box.removed.any():
        return np.zeros_like(air)
    lab, n = ndimage.label(inside)
    touch = np.unique(lab[face_adjacent(box.removed) & inside])
    touch = touch[touch > 0]
    out = np.isin(lab, touch)
    near = box.distance_to("removed", box.removed) <= reach_mm
    out &= near
    if eye_mm is not None and out.any():
        ijk = np.argwhere(out)
        seen = clear_to_eye(box, ijk, eye_mm, box.occluder, step_voxels)
        out[tuple(ijk[~seen].T)] = False
    return out


def surface_of(box: Box, mask: np.ndarray) -> np.ndarray:
    """A structure's surface in the box (module docstring), bool."""
    return np.asarray(mask, bool) & face_adjacent(box.bone0)


def thinnest(cover: np.ndarray, h: float, min_area_mm2: float) -> float:
    """The least cover over at least ``min_area_mm2`` (module docstring) [mm]."""
    k = max(1, int(math.ceil(min_area_mm2 / (h * h) - 1e-9)))
    if len(cover) < k:
        return math.inf
    return float(np.partition(np.asarray(cover, float), k - 1)[k - 1])


def cover_quantities(box: Box, surface: np.ndarray, params: dict, thin_mm: float,
                     drilled_only: bool = False) -> dict:
    """Cover of a surface: ``thinnest_mm``, ``exposed_mm2``, ``thinned_mm2``
    (cover at most ``thin_mm``), ``surface_mm2`` and, for the picture,
    ``_cover`` (per surface voxel [mm]) and ``_ijk`` (box voxels). With
    ``drilled_only`` the cover is measured to the removed voxels alone (the
    ear canal's wall: air cells next to the canal are the anatomy's)."""
    d = box.distance_to("removed", box.removed) if drilled_only else \
        box.distance_to("cavity", box.cavity)
    ijk = np.argwhere(surface)
    cov = np.maximum(d[tuple(ijk.T)] - box.h, 0.0) if len(ijk) else np.zeros(0)
    dr = box.distance_to("removed", box.removed)[tuple(ijk.T)] if len(ijk) else cov
    a = box.h * box.h
    return {"thinnest_mm": thinnest(cov, box.h, params["min_area_mm2"]),
            "exposed_mm2": float(np.count_nonzero(dr <= box.h) * a),
            "thinned_mm2": float(np.count_nonzero(cov <= thin_mm) * a),
            "surface_mm2": float(len(cov) * a), "_cover": cov, "_ijk": ijk}


def occluder(box: Box, params: dict) -> np.ndarray:
    """Remaining tissue more than ``occluder_depth_voxels`` face steps from
    the removed voxels (module docstring), box voxels, bool."""
    depth = int(params["occluder_depth_voxels"])
    if depth <= 0 or not box.removed.any():
        return box.present
    return box.present & ~ndimage.binary_dilation(box.removed, iterations=depth)


def clear_to_eye(box: Box, ijk, eye_mm, occ, step_voxels: float, hits=None) -> np.ndarray:
    """Whether the sight line from each box voxel ``ijk`` (n, 3) to the eye
    misses ``occ`` (module docstring), (n,) bool; the occluder voxels the
    blocked lines meet are set in ``hits`` (bool, box shape) when given."""
    ijk = np.asarray(ijk).reshape(-1, 3)
    shape = np.array(occ.shape)
    n_steps = int(math.ceil(float(np.linalg.norm(shape)) / step_voxels)) + 1
    eye_v = (np.asarray(eye_mm, float) - box.origin_mm) / box.h   # eye in box voxels
    ts = step_voxels * np.arange(1, n_steps + 1)
    seen = np.zeros(len(ijk), bool)
    for c0 in range(0, len(ijk), _CHUNK):
        p = ijk[c0:c0 + _CHUNK].astype(float)
        d = eye_v - p
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        q = np.rint(p[:, None, :] + ts[None, :, None] * d[:, None, :]).astype(np.int64)
        inside = np.all((q >= 0) & (q < shape), axis=2) & (ts[None, :] < dist[:, None])
        qc = np.where(inside[..., None], q, 0)
        blocked = occ[qc[..., 0], qc[..., 1], qc[..., 2]] & inside
        any_b = blocked.any(axis=1)
        seen[c0:c0 + _CHUNK] = ~any_b
        if hits is not None and any_b.any():
            b = qc[blocked]
            hits[b[:, 0], b[:, 1], b[:, 2]] = True
    return seen


def sightlines(box: Box, eye_mm, params: dict) -> dict:
    """Overhang and hidden wall (module docstring).

    Returns
    -------
    dict
        ``overhang_mm3``, ``hidden_wall_share`` (NaN without a wall),
        ``wall_voxels``; for the picture ``_overhang`` and ``_hidden`` (box
        voxel indices (n, 3)).
    """
    h = box.h
    depth = int(params["occluder_depth_voxels"])
    occ = occluder(box, params) if box.occluder is None else box.occluder
    starts = box.removed & face_adjacent(box.present)
    wall = box.present & face_adjacent(box.removed)
    ijk = np.argwhere(starts)
    hit = np.zeros(box.present.shape, bool)
    seen = clear_to_eye(box, ijk, eye_mm, occ, float(params["step_voxels"]), hit)
    if depth > 0 and hit.any():
        hit = ndimage.binary_dilation(hit, iterations=depth, mask=box.present)
    seen_vox = np.zeros(box.present.shape, bool)
    seen_vox[tuple(ijk[seen].T)] = True
    wall_seen = wall & face_adjacent(seen_vox)
    n_wall = int(np.count_nonzero(wall))
    hidden = wall & ~wall_seen
    return {"overhang_mm3": float(np.count_nonzero(hit) * h ** 3),
            "hidden_wall_share": float(np.count_nonzero(hidden) / n_wall) if n_wall
            else float("nan"), "wall_voxels": n_wall,
            "_overhang": np.argwhere(hit), "_hidden": np.argwhere(hidden)}


def ball_mask(box: Box, centre_mm, radius_mm: float) -> np.ndarray:
    """Box voxels whose centre lies within ``radius_mm`` of ``centre_mm``."""
    c = (np.asarray(centre_mm, float) - box.origin_mm) / box.h
    r = radius_mm / box.h
    lo = np.maximum(np.floor(c - r).astype(int), 0)
    hi = np.minimum(np.ceil(c + r).astype(int) + 1, box.present.shape)
    out = np.zeros(box.present.shape, bool)
    if np.any(hi <= lo):
        return out
    g = np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij")
    d2 = sum((gi - ci) ** 2 for gi, ci in zip(g, c))
    out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = d2 <= r * r
    return out


def antrum_region(box: Box, centre_mm, radius_mm: float, found: bool,
                  params: dict) -> np.ndarray:
    """The antrum's voxels: the air component at its centre within its radius
    plus ``antrum_extra_mm`` (found), else a ball of
    ``antrum_estimated_radius_mm``."""
    if not found:
        return ball_mask(box, centre_mm, params["antrum_estimated_radius_mm"])
    air = ball_mask(box, centre_mm, radius_mm + params["antrum_extra_mm"]) & ~box.tissue0
    lab, _ = ndimage.label(air)
    c = box.index_of(centre_mm)[0]
    if np.all((c >= 0) & (c < air.shape)) and lab[tuple(c)] > 0:
        return lab == lab[tuple(c)]
    return air


def antrum_quantities(box: Box, region: np.ndarray) -> dict:
    """``gap_mm`` (bone between the antrum and the nearest removed voxel:
    ``max(0, d - h)``, 0 when they touch face to face) and ``opening_mm2``
    (antrum voxels face to face with removed ones, ``h^2`` each)."""
    if not region.any():
        return {"gap_mm": math.inf, "opening_mm2": 0.0}
    d = box.distance_to("removed", box.removed)
    gap = max(0.0, float(d[region].min()) - box.h)
    opening = np.count_nonzero(region & face_adjacent(box.removed)) * box.h ** 2
    return {"gap_mm": gap, "opening_mm2": float(opening)}


def angle_gap(box: Box) -> dict:
    """``gap_mm``: over the removed voxels, the least of the larger of their
    distances to the sinus and to the tegmen, less ``h`` (0 when a removed
    voxel touches both); and ``_at`` (that voxel, box index)."""
    s, t = box.groups.get("sinus"), box.groups.get("tegmen")
    if s is None or t is None or not s.any() or not t.any() or not box.removed.any():
        return {"gap_mm": math.inf, "_at": None}
    far = np.maximum(box.distance_to("sinus", s), box.distance_to("tegmen", t))
    far = np.where(box.removed, far, np.inf)
    q = np.unravel_index(int(np.argmin(far)), far.shape)
    return {"gap_mm": max(0.0, float(far[q]) - box.h), "_at": np.array(q)}


def reach_gap(box: Box, target: np.ndarray) -> dict:
    """``gap_mm``: bone between a target's voxels and the cavity (``max(0, d -
    h)`` at the nearest one; inf when it is not in the box)."""
    if target is None or not target.any():
        return {"gap_mm": math.inf}
    d = box.distance_to("cavity", box.cavity)
    return {"gap_mm": max(0.0, float(d[target].min()) - box.h)}


def tip_gap(box: Box, tip_z_mm: float) -> dict:
    """``gap_mm``: how far above the mastoid tip's height the lowest removed
    bone voxel lies [mm] (0 at or below it; inf when no bone was removed)."""
    rb = box.removed & box.bone0
    if not rb.any():
        return {"gap_mm": math.inf, "_at": None}
    k = np.argwhere(rb)
    low = k[np.argmin(k[:, 2])]
    z = float(box.origin_mm[2] + box.h * low[2])
    return {"gap_mm": max(0.0, z - float(tip_z_mm)), "_at": low}


def injury_quantities(box: Box, mask: np.ndarray, show_exposed: bool = True) -> dict:
    """``removed_mm3`` (the structure's voxels removed) and ``exposed_mm2``
    (its surface face to face with a removed voxel); ``_ijk`` the removed
    voxels and (``show_exposed``) the exposed ones, for the picture."""
    m = np.asarray(mask, bool)
    rem = m & box.removed
    d = box.distance_to("removed", box.removed)
    exposed = surface_of(box, m) & (d <= box.h)
    return {"removed_mm3": float(np.count_nonzero(rem) * box.h ** 3),
            "exposed_mm2": float(np.count_nonzero(exposed) * box.h ** 2),
            "_ijk": np.argwhere(rem | (exposed if show_exposed else False))}
