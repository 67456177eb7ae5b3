"""Scripted final products of the phantom for the assessment tests: the
planned mastoidectomy carved straight into the tissue (each drilling sample
removes the voxels whose centres its burr's sphere holds: no haptic
simulation), and edits of it that satisfy or violate one item at a time.

Every builder returns ``present``, the (nx, ny, nz) bool tissue left at the
end, on the phantom's engine grid (0.5 mm).
"""
from __future__ import annotations

import functools

import numpy as np


class Phantom:
    """The phantom's arrays, landmarks and camera."""

    def __init__(self):
        from bonesim.io.case import load_case

        self.case = load_case("phantom")
        vol = self.case.load_volume()
        self.labels = vol.labels
        self.h = float(vol.spacing_mm)
        self.origin = np.asarray(vol.origin_mm, float)
        self.structures = self.case.structures
        self.lm = self.case.landmarks
        self.eye = np.asarray(self.case.camera.eye_mm, float)
        self.view = np.asarray(self.case.camera.focal_mm, float) - self.eye
        self.view /= np.linalg.norm(self.view)
        self.tissue0 = self.labels > 0
        self.bone0 = self.labels == 1
        ijk = np.indices(self.labels.shape).reshape(3, -1).T
        self.centres = (self.origin + self.h * ijk).reshape(self.labels.shape + (3,))

    def label(self, name: str) -> int:
        return next(s for s, st in enumerate(self.structures, start=1) if st.name == name)

    def assess(self, present):
        from metrics.assessment import assess_tissue

        return assess_tissue(self.labels, present, self.h, self.origin, self.structures,
                             self.lm, self.eye, case="phantom")

    def dist_to(self, mask) -> np.ndarray:
        """Distance [mm] from every voxel centre to ``mask``."""
        from scipy import ndimage

        return ndimage.distance_transform_edt(~np.asarray(mask, bool), sampling=self.h)


@functools.lru_cache(maxsize=1)
def phantom() -> Phantom:
    return Phantom()


def carve(ph: Phantom, pos_mm, radii_mm) -> np.ndarray:
    """(nx, ny, nz) bool: voxels whose centre lies within the radius of some
    sphere (centres ``pos_mm`` (n, 3) [mm], radii (n,) [mm])."""
    out = np.zeros(ph.labels.shape, bool)
    pos = np.asarray(pos_mm, float).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(radii_mm, float), (len(pos),))
    for r in np.unique(radii):
        p = pos[radii == r]
        n = int(np.ceil(r / ph.h)) + 1
        off = np.indices((2 * n + 1,) * 3).reshape(3, -1).T - n
        for c0 in range(0, len(p), 512):
            pc = p[c0:c0 + 512]
            base = np.rint((pc - ph.origin) / ph.h).astype(np.int64)
            q = base[:, None, :] + off[None, :, :]
            cen = ph.origin + ph.h * q
            inside = np.sum((cen - pc[:, None, :]) ** 2, axis=2) <= r * r
            inside &= np.all((q >= 0) & (q < ph.labels.shape), axis=2)
            v = q[inside]
            out[v[:, 0], v[:, 1], v[:, 2]] = True
    return out


@functools.lru_cache(maxsize=1)
def _plan():
    from bonesim.io.toolpath import plan_mastoidectomy

    return plan_mastoidectomy(phantom().case)


@functools.lru_cache(maxsize=4)
def planned_present(keep_off: str | None = None, keep_mm: float = 0.0) -> np.ndarray:
    """The phantom's planned mastoidectomy (the main job's plan: cutting burr,
    then diamond burr) carved into the tissue: its drilling samples, every
    0.1 mm of travel; with ``keep_off``, without the samples whose burr comes
    within ``keep_mm`` of that structure (a run that stays off it)."""
    from bonesim.io.burrs import load_burr

    ph = phantom()
    run = _plan()
    tr = run.trajectory
    radii = np.array([load_burr(b).radius_mm for b in run.burrs])[tr.burr]
    on = tr.drill.astype(bool)
    pos, rad = tr.pos_mm[on], radii[on]
    if keep_off is not None:
        d = ph.dist_to(ph.labels == ph.label(keep_off))
        q = np.clip(np.rint((pos - ph.origin) / ph.h).astype(int), 0,
                    np.array(ph.labels.shape) - 1)
        ok = d[tuple(q.T)] - rad - ph.h >= keep_mm
        pos, rad = pos[ok], rad[ok]
    keep = np.ones(len(pos), bool)
    last = pos[0]
    for q in range(1, len(pos)):            # every 0.1 mm of travel
        if np.sum((pos[q] - last) ** 2) < 0.01 and rad[q] == rad[q - 1]:
            keep[q] = False
        else:
            last = pos[q]
    cut = carve(ph, pos[keep], rad[keep])
    return ph.tissue0 & ~(cut & ph.tissue0)


# --------------------------------------------------------------- the edits
def _removed(ph, present):
    return ph.tissue0 & ~present


def expose_sinus(present, enter: bool = False) -> np.ndarray:
    """Drill the bone off the sinus where it is thinnest (a 1.5 mm ball of
    bone around the sinus surface voxel nearest the cavity); with
    ``enter``, into the sinus too."""
    ph = phantom()
    sinus = ph.labels == ph.label("sigmoid_sinus")
    d = ph.dist_to(_removed(ph, present))
    surf = sinus & _face_adjacent(ph.bone0)
    q = np.unravel_index(np.argmin(np.where(surf, d, np.inf)), d.shape)
    ball = np.sum((ph.centres - ph.centres[q]) ** 2, axis=3) <= 1.5 ** 2
    out = present.copy()
    out[ball & (ph.bone0 | (sinus if enter else False))] = False
    return out


def overhang(present, depth_mm: float = 2.5) -> np.ndarray:
    """Put a lid back: the removed bone less than ``depth_mm`` under the
    cortex in the cavity's posterosuperior quadrant (an undercut rim; not
    over the antrum, which a lid would hide with the lateral canal)."""
    ph = phantom()
    rem = _removed(ph, present) & ph.bone0
    c = ph.centres
    cx = ph.lm.cortex
    j = np.clip(np.rint((c[..., 1] - cx["y0"]) / cx["h"]).astype(int), 0,
                cx["height"].shape[0] - 1)
    k = np.clip(np.rint((c[..., 2] - cx["z0"]) / cx["h"]).astype(int), 0,
                cx["height"].shape[1] - 1)
    depth = cx["height"][j, k] - c[..., 0]          # left ear: lateral is +x
    ys, zs = c[..., 1][rem], c[..., 2][rem]
    lid = rem & (depth < depth_mm) & (c[..., 1] > np.median(ys)) & (c[..., 2] > np.median(zs))
    out = present.copy()
    out[lid] = True
    return out


def short_of_antrum(present, keep_mm: float = 3.0) -> np.ndarray:
    """Stop short of the antrum: put back the removed bone within ``keep_mm``
    of the antrum's air."""
    ph = phantom()
    a = ph.lm.get("antrum")
    c = np.asarray(a.point_mm)
    air = (~ph.tissue0) & (np.sum((ph.centres - c) ** 2, axis=3)
                           <= (a.detail["radius_mm"] + 1.0) ** 2)
    near = ph.dist_to(air) <= keep_mm
    out = present.copy()
    out[near & ph.bone0] = True
    return out


def perforate_canal(present, lumen, radius_mm: float = 0.75) -> np.ndarray:
    """Drill through the posterior canal wall where it is thinnest (away from
    the chorda tympani, which runs behind the wall): a shaft along the line
    of sight down to the canal's lumen at its voxel nearest the cavity."""
    ph = phantom()
    d = ph.dist_to(_removed(ph, present))
    far = ph.dist_to(ph.labels == ph.label("chorda_tympani")) > 3.0
    q = np.unravel_index(np.argmin(np.where(lumen & far, d, np.inf)), d.shape)
    return _shaft(present, ph.centres[q], radius_mm, ph.bone0)


def _shaft(present, p0, radius_mm, removable):
    """Remove ``removable`` within ``radius_mm`` of the line of sight through
    ``p0`` [mm], from ``p0`` toward the eye."""
    ph = phantom()
    rel = ph.centres - p0
    t = rel @ -ph.view                          # toward the eye
    off = rel + t[..., None] * ph.view
    shaft = (t >= -0.3) & (t <= 30.0) & (np.sum(off ** 2, axis=3) <= radius_mm ** 2)
    out = present.copy()
    out[shaft & removable] = False
    return out


def drill_into(present, structure: str, radius_mm: float = 1.0) -> np.ndarray:
    """A shaft along the line of sight from the cavity into a structure at its
    voxel nearest the cavity (bone and structure within ``radius_mm`` of
    the shaft's axis, from the structure's voxel out to the eye's side)."""
    ph = phantom()
    s = ph.labels == ph.label(structure)
    d = ph.dist_to(_removed(ph, present))
    q = np.unravel_index(np.argmin(np.where(s, d, np.inf)), d.shape)
    return _shaft(present, ph.centres[q], radius_mm, ph.bone0 | s)


def _face_adjacent(mask):
    from metrics.assessment_measure import face_adjacent

    return face_adjacent(mask)
