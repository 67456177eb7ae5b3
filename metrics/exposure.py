"""Exposure: how much of a structure a run left under thin bone.

A mastoidectomy skeletonizes the sigmoid sinus, the tegmen (over the middle
fossa dura) and the facial nerve: it thins the bone over them without
opening it. This measures, at the end of a run, how much of each structure's
bone-covered surface is left under less than 1 mm and 0.5 mm of bone.

Definitions
-----------
Surface
    The structure's voxels with at least one of their 6 face neighbours
    labelled bone (a structure of kind ``"bone"``) in the case's initial
    grid: the part of the structure that bone covers.
Drilled region
    The voxels removed in the run's last epoch (as in :mod:`metrics.regions`:
    a reset puts the tissue back).
Cover [mm]
    Per surface voxel ``v``: ``max(0, min_r |c_v - c_r| - h)`` over the
    drilled voxels ``r``, with voxel centres ``c`` and voxel edge ``h``: the
    bone left between the voxel and the nearest point of the drilled cavity
    along the line joining their centres (face-adjacent to the cavity: 0;
    one voxel of bone between: ``h``). Infinite when nothing was drilled.
    Bone that was already missing (air cells) does not count as drilled: the
    metric is about what the run did.
Exposed fractions
    Per threshold ``x`` (default :data:`THRESHOLDS_MM`), the fraction of the
    surface with cover ``< x``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from metrics.forces import structure_label
from metrics.regions import drilled_voxels, final_epoch

__all__ = ["DEFAULT_STRUCTURES", "THRESHOLDS_MM", "Exposure", "structure_surface",
           "cover_mm", "exposure"]

#: Structures a mastoidectomy skeletonizes (the tegmen covers the middle
#: fossa dura).
DEFAULT_STRUCTURES = ("sigmoid_sinus", "middle_fossa_dura", "facial_nerve")
#: Remaining-bone thresholds [mm].
THRESHOLDS_MM = (1.0, 0.5)


def structure_surface(labels, label: int, bone_labels) -> np.ndarray:
    """Voxels ``(m, 3)`` (int64, x, y, z order) of structure ``label`` with a
    face neighbour whose label is in ``bone_labels``.

    Raises
    ------
    ValueError
        If ``labels`` is not a 3-D integer array.
    """
    lab = np.asarray(labels)
    if lab.ndim != 3 or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"labels must be a 3-D integer array, got {lab.dtype} {lab.shape}")
    bone = np.isin(lab, np.asarray(list(bone_labels), dtype=lab.dtype))
    near = np.zeros_like(bone)
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        near[tuple(lo)] |= bone[tuple(hi)]
        near[tuple(hi)] |= bone[tuple(lo)]
    return np.argwhere((lab == label) & near).astype(np.int64)


def cover_mm(surface_ijk, drilled_ijk, voxel_mm: float) -> np.ndarray:
    """Bone cover [mm] of each surface voxel over the drilled voxels (module
    notes); ``(m,)``, inf when nothing was drilled.

    Raises
    ------
    ValueError
        On a non-positive ``voxel_mm`` or index arrays not of shape (n, 3).
    """
    h = float(voxel_mm)
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"voxel_mm must be a positive number, got {voxel_mm!r}")
    s = np.asarray(surface_ijk, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(drilled_ijk, dtype=np.float64).reshape(-1, 3)
    if not len(d):
        return np.full(len(s), np.inf)
    if not len(s):
        return np.zeros(0)
    dist, _ = cKDTree(d * h).query(s * h)
    return np.maximum(0.0, dist - h)


@dataclass(frozen=True)
class Exposure:
    """One structure's exposure at the end of a run.

    Attributes
    ----------
    structure : str
    surface : int
        Surface voxels (bone-covered).
    thresholds_mm : tuple of float
    fraction : tuple of float
        Per threshold, the fraction of the surface under less bone (NaN for
        a structure without surface).
    count : tuple of int
        Per threshold, the surface voxels under less bone.
    cover_mm : (surface,) float64
        Each surface voxel's cover [mm].
    """

    structure: str
    surface: int
    thresholds_mm: tuple
    fraction: tuple
    count: tuple
    cover_mm: np.ndarray


def exposure(session, structures=DEFAULT_STRUCTURES, *, thresholds_mm=THRESHOLDS_MM,
             model=None, labels=None) -> dict:
    """Per structure, the share of its bone-covered surface left under thin bone.

    Parameters
    ----------
    session : bonesim.session.reader.Session
        Uses ``header`` (``structures``, ``shape``, ``voxel_mm``, ``case``),
        ``removals`` and ``samples["epoch"]``.
    structures : sequence of str
        Structure names of the case.
    thresholds_mm : sequence of float
        Positive bone thicknesses [mm].
    model : bonesim.engine.model.Model, optional
        The session's model (default ``session.load_model()``); its grid's
        labels are the initial tissue.
    labels : (nx, ny, nz) uint8, optional
        The initial label map itself (instead of a model).

    Returns
    -------
    dict of str -> Exposure

    Raises
    ------
    ValueError
        On an unknown structure (naming the case's), a non-positive
        threshold, or labels not of the header's shape.
    """
    h = session.header
    case = h.get("case", {}).get("name", "")
    th = tuple(float(x) for x in thresholds_mm)
    if not th or any(not (np.isfinite(x) and x > 0) for x in th):
        raise ValueError(f"thresholds_mm must be positive numbers, got {thresholds_mm!r}")
    wanted = [(name, structure_label(h["structures"], name, case)) for name in structures]
    if labels is None:
        model = session.load_model() if model is None else model
        labels = model.grid.to_dense()[1]
    labels = np.asarray(labels)
    shape = tuple(int(x) for x in h["shape"])
    if labels.shape != shape:
        raise ValueError(f"labels has shape {labels.shape}, the session's grid {shape}")
    bone = [int(st["label"]) for st in h["structures"] if st.get("kind") == "bone"]
    rem = session.removals
    last = final_epoch(session)
    flat = drilled_voxels(rem["ijk"][rem["epoch"] == last], last, shape)
    drilled = np.column_stack(np.unravel_index(flat, shape)) if len(flat) else \
        np.zeros((0, 3), np.int64)
    out = {}
    for name, lab in wanted:
        surf = structure_surface(labels, lab, bone)
        cov = cover_mm(surf, drilled, float(h["voxel_mm"]))
        cnt = tuple(int(np.sum(cov < x)) for x in th)
        frac = tuple(c / len(surf) if len(surf) else float("nan") for c in cnt)
        out[name] = Exposure(name, len(surf), th, frac, cnt, cov)
    return out
