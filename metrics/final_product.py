"""The final product: a run's drilled cavity against expert runs of the same case.

After Ohio State's comparison of trainee-drilled with expert-drilled bones and
the Visible Ear Simulator's automated final-product assessment: what matters
at the end is *which* bone is gone. A run's drilled set ``D`` is the voxels
removed in its last epoch (:func:`metrics.regions.drilled_voxels`, flat
indices over the case grid); an expert's ``E`` likewise.

Measures
--------
Overlap
    Dice ``2 |D & E| / (|D| + |E|)`` and Jaccard ``|D & E| / |D | E|`` (1 when
    both are empty), overall and per *region*: the voxels within each band of
    distance from each critical structure (:data:`BANDS_MM`, as
    :mod:`metrics.conduct`), where over-drilling costs most.
Missed and extra [mm^3]
    ``|E - D|`` (bone the expert took and the run left) and ``|D - E|`` (bone
    the run took that the expert left), times the voxel volume.
Distance between cavities [mm]
    From every voxel of one set to the nearest voxel of the other, both
    ways: the mean of the two directed means (average symmetric distance)
    and the 95th percentile of all of them (a Hausdorff distance robust to
    a stray voxel). Exact Euclidean distances between voxel centres
    (:class:`scipy.spatial.cKDTree`). NaN when a set is empty.
Against several experts
    Each measure against each expert, and their mean: an expert panel,
    not one reference.
"""
from __future__ import annotations

import numpy as np

__all__ = ["BANDS_MM", "HAUSDORFF_PERCENTILE", "overlap", "cavity_distance", "band_of_voxels",
           "compare", "drilled_set", "compare_to_experts"]

#: Edges [mm] of the distance bands from a critical structure (regions).
BANDS_MM = (2.0, 5.0)
#: Percentile of the point-to-set distances reported as the robust Hausdorff distance.
HAUSDORFF_PERCENTILE = 95.0


def _flat(a) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"drilled sets must be 1-D arrays of flat voxel indices, got "
                         f"{a.dtype} {a.shape}")
    return np.unique(a.astype(np.int64))


def overlap(d, e) -> dict:
    """Dice, Jaccard, and the voxel counts of two drilled sets.

    Parameters
    ----------
    d, e : (n,) int
        Flat voxel indices (duplicates are ignored).

    Returns
    -------
    dict
        ``dice``, ``jaccard``, ``both``, ``missed`` (in ``e`` only), ``extra``
        (in ``d`` only) [voxels].
    """
    d, e = _flat(d), _flat(e)
    both = int(np.intersect1d(d, e, assume_unique=True).size)
    union = len(d) + len(e) - both
    return {"dice": 2.0 * both / (len(d) + len(e)) if len(d) + len(e) else 1.0,
            "jaccard": both / union if union else 1.0,
            "both": both, "missed": len(e) - both, "extra": len(d) - both}


def _centres(flat, shape, voxel_mm):
    return np.stack(np.unravel_index(flat, shape), axis=1).astype(float) * float(voxel_mm)


def cavity_distance(d, e, shape, voxel_mm: float,
                    percentile: float = HAUSDORFF_PERCENTILE) -> dict:
    """Distances between two drilled sets (module docstring).

    Parameters
    ----------
    d, e : (n,) int
        Flat voxel indices over a grid of ``shape``.
    shape : (3,) int
    voxel_mm : float
        Voxel edge [mm].
    percentile : float
        Of the pooled point-to-set distances, in [0, 100].

    Returns
    -------
    dict
        ``mean_mm`` (average symmetric distance), ``hausdorff_mm`` (the
        percentile); NaN when a set is empty.
    """
    from scipy.spatial import cKDTree

    if not 0.0 <= percentile <= 100.0:
        raise ValueError(f"percentile must lie in [0, 100], got {percentile}")
    d, e = _flat(d), _flat(e)
    if len(d) == 0 or len(e) == 0:
        return {"mean_mm": float("nan"), "hausdorff_mm": float("nan")}
    pd, pe = _centres(d, shape, voxel_mm), _centres(e, shape, voxel_mm)
    de, _ = cKDTree(pe).query(pd)
    ed, _ = cKDTree(pd).query(pe)
    return {"mean_mm": 0.5 * (float(de.mean()) + float(ed.mean())),
            "hausdorff_mm": float(np.percentile(np.concatenate([de, ed]), percentile))}


def band_of_voxels(flat, shape, voxel_mm: float, origin_mm, clearance, labels,
                   bands_mm=BANDS_MM) -> np.ndarray:
    """The region of each voxel: its band of distance from each structure.

    Returns
    -------
    (n, k) int
        Band index per structure of ``labels``: 0 for ``[0, b0)``, ... ,
        ``len(bands_mm)`` beyond the last edge.
    """
    flat = _flat(flat)
    if len(flat) == 0:
        return np.zeros((0, len(labels)), np.int64)
    c = np.asarray(origin_mm, float) + _centres(flat, shape, voxel_mm)
    dist = clearance.distances(c, [[int(s)] for s in labels])
    return np.searchsorted(np.asarray(bands_mm, float), dist, side="right")


def compare(d, e, shape, voxel_mm: float, *, regions=None) -> dict:
    """Every measure of the module docstring for one pair of drilled sets.

    Parameters
    ----------
    d, e : (n,) int
        The run's and the expert's drilled sets (flat indices).
    shape : (3,) int
    voxel_mm : float
    regions : callable, optional
        ``regions(flat) -> (n, k)`` region index per voxel and structure
        (e.g. :func:`band_of_voxels` bound to a case), and its attribute
        ``names`` (k structure names) and ``bands`` (band labels); with
        it, the overlap per region.

    Returns
    -------
    dict
    """
    d, e = _flat(d), _flat(e)
    v = float(voxel_mm) ** 3
    ov = overlap(d, e)
    out = {"dice": ov["dice"], "jaccard": ov["jaccard"], "missed_mm3": ov["missed"] * v,
           "extra_mm3": ov["extra"] * v, **cavity_distance(d, e, shape, voxel_mm)}
    if regions is not None:
        rd, re_ = regions(d), regions(e)
        per = {}
        for c, name in enumerate(regions.names):
            per[name] = {}
            for b, band in enumerate(regions.bands):
                o = overlap(d[rd[:, c] == b], e[re_[:, c] == b])
                per[name][band] = {"dice": o["dice"], "missed_mm3": o["missed"] * v,
                                   "extra_mm3": o["extra"] * v}
        out["regions"] = per
    return out


def drilled_set(session) -> np.ndarray:
    """The run's drilled set: flat indices of the voxels removed in its last
    epoch (:func:`metrics.conduct.last_epoch`, :func:`metrics.regions.drilled_voxels`)."""
    from metrics.conduct import last_epoch
    from metrics.regions import drilled_voxels

    _, rem = last_epoch(session)
    return drilled_voxels(rem["ijk"], 0, session.header["shape"])


class _Regions:
    """:func:`band_of_voxels` bound to a case (for :func:`compare`)."""

    def __init__(self, model, shape, voxel_mm, origin_mm, bands_mm=BANDS_MM):
        self.labels = [k for k, s in enumerate(model.structures, start=1)
                       if s.kind != "bone"]
        self.names = [model.structures[k - 1].name for k in self.labels]
        edges = [0.0, *bands_mm]
        self.bands = [f"{lo:g}-{hi:g} mm" for lo, hi in zip(edges, bands_mm)] + \
            [f">= {bands_mm[-1]:g} mm"]
        self._args = (shape, voxel_mm, origin_mm, model.clearance, self.labels, bands_mm)

    def __call__(self, flat):
        return band_of_voxels(flat, *self._args)


def compare_to_experts(session, experts, *, model=None, regions: bool = True) -> dict:
    """A run's final product against a panel of expert runs of its case.

    Parameters
    ----------
    session : Session
        The run.
    experts : sequence of Session
        Expert runs of the same case (same grid).
    model : Model, optional
        The case's model (default ``session.load_model()``): its clearance
        gives the regions.
    regions : bool
        Also the overlap per region.

    Returns
    -------
    dict
        ``per_expert``: a list of :func:`compare` results (with the expert's
        participant), ``mean``: the mean of each overall measure.

    Raises
    ------
    ValueError
        If an expert run is of another case or grid, or there is none.
    """
    if not experts:
        raise ValueError("compare_to_experts needs at least one expert run")
    h = session.header
    shape, voxel = tuple(h["shape"]), float(h["voxel_mm"])
    me = drilled_set(session)
    reg = None
    if regions:
        model = session.load_model() if model is None else model
        if model.clearance is not None:
            reg = _Regions(model, shape, voxel, h["origin_mm"])
    per = []
    for ex in experts:
        eh = ex.header
        if eh["case"]["name"] != h["case"]["name"] or tuple(eh["shape"]) != shape:
            raise ValueError(f"expert run {getattr(ex, 'path', '?')} is of case "
                             f"{eh['case']['name']!r} {tuple(eh['shape'])}, not "
                             f"{h['case']['name']!r} {shape}")
        res = compare(me, drilled_set(ex), shape, voxel, regions=reg)
        res["expert"] = str(eh.get("participant", ""))
        per.append(res)
    keys = ("dice", "jaccard", "missed_mm3", "extra_mm3", "mean_mm", "hausdorff_mm")
    return {"per_expert": per,
            "mean": {k: _nanmean([p[k] for p in per]) for k in keys}}


def _nanmean(values) -> float:
    v = np.asarray(values, float)
    v = v[~np.isnan(v)]
    return float(v.mean()) if len(v) else float("nan")
