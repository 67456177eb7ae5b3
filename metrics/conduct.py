"""How a run was drilled: the measures later simulators report beside the
reference's (Western Ontario's real-time metrics, the Visible Ear
Simulator's assessment, Ohio State's comparisons).

All are pure functions of a recorded session (:func:`bonesim.session.reader.read_session`)
over its **last epoch** (the samples and removals after the last case reset:
what the run left), in the case frame.

Definitions
-----------
Drilling sample
    A haptic step with the drill running and the burr in bone
    (``volume_mm3 > 0``).
Stroke
    A maximal run of consecutive drilling samples, at least
    :data:`MIN_STROKE_S` long. Its *path* is the summed burr travel [mm], its
    *chord* the distance from its first to its last burr centre [mm],
    *straightness* chord / path, and its *plunge* ``|cos|`` of the angle
    between the chord and the line of sight (the case camera's, from eye to
    focal point): 0 for a sweep across the field, 1 for a plunge along the
    view. Stroke *consistency* is the coefficient of variation (sd / mean) of
    the stroke paths (lower: more regular strokes).
Force [N]
    ``|force_n - vibration_n|``, the force rendered to the hand without the
    synthesized vibration (as :mod:`metrics.forces`).
Excessive-force event
    A maximal run of samples whose force is at least
    :data:`EXCESSIVE_SHARE` of the force limit of the step (the lower of the
    device's maximum and the burr's, the force the simulator clamps to:
    the bone pushed back as hard as it can be rendered), lasting at least
    :data:`MIN_EVENT_S`: start [s], duration [s], peak [N].
Burr gap [mm]
    From the burr's surface (centre distance minus the sample's burr
    radius) to a structure's voxels, exact on the case's label map
    (:class:`bonesim.physics.clearance.Clearance`).
Time near a structure [s]
    Drilling time with the burr gap to it below each of :data:`NEAR_MM`.
Drilled volume [mm^3]
    Removed voxels times the voxel volume, per structure label, and per
    band of distance from each critical structure (:data:`BANDS_MM`).
Burr per stage
    The drilling time is cut into :data:`N_STAGES` equal stages; per stage
    the share of drilling time with each burr. Also the mean burr diameter
    while drilling with the burr gap to a critical structure under and over
    :data:`NEAR_BURR_MM`.
"""
from __future__ import annotations

import numpy as np

from metrics.regions import final_epoch

__all__ = ["MIN_STROKE_S", "MIN_EVENT_S", "EXCESSIVE_SHARE", "NEAR_MM", "BANDS_MM",
           "N_STAGES", "NEAR_BURR_MM", "last_epoch", "drilling_mask", "strokes",
           "stroke_summary", "excessive_force_events", "burr_gaps", "time_near",
           "drilled_volume", "burr_stages", "injuries_by_structure", "conduct"]

#: Shortest stroke [s].
MIN_STROKE_S = 0.05
#: Shortest excessive-force event [s].
MIN_EVENT_S = 0.02
#: Force at or above this share of the device's maximum is excessive.
EXCESSIVE_SHARE = 0.95
#: Burr gaps [mm] under which drilling time counts as near a structure.
NEAR_MM = (1.0, 2.0)
#: Distance bands [mm] from a critical structure for the drilled volume.
BANDS_MM = (2.0, 5.0, 10.0)
#: Stages of the drilling time for the burr choice.
N_STAGES = 3
#: Burr gap [mm] that splits "near" from "far" for the burr size used.
NEAR_BURR_MM = 3.0


def last_epoch(session):
    """``(samples, removals)`` of the session's last epoch (dicts of columns);
    the removals are the drilled ones (specks shed as dust are left out)."""
    s = session.samples
    r = session.removals
    last = final_epoch(session)
    ks = s["epoch"] == last
    # a speck shed as dust with a cut-off fragment is not drilled (events.REMOVED_SHED)
    kr = (r["epoch"] == last) & ~np.asarray(r.get("shed", np.zeros(len(r["epoch"]), bool)),
                                            bool)
    return {k: v[ks] for k, v in s.items()}, {k: v[kr] for k, v in r.items()}


def drilling_mask(samples) -> np.ndarray:
    """(n,) bool: the drill runs and the burr is in bone."""
    return (np.asarray(samples["drill"]) != 0) & (np.asarray(samples["volume_mm3"]) > 0.0)


def _runs(mask):
    """``(start, stop)`` index pairs of the runs of True in ``mask``."""
    m = np.concatenate(([False], np.asarray(mask, bool), [False]))
    d = np.diff(m.astype(np.int8))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def strokes(samples, view, min_s: float = MIN_STROKE_S) -> dict:
    """The strokes of a run (module docstring).

    Parameters
    ----------
    samples : dict
        Session samples (``t_s``, ``pos_mm``, ``drill``, ``volume_mm3``).
    view : (3,) float
        Line of sight (eye to focal point); normalized here.
    min_s : float
        Shortest stroke [s].

    Returns
    -------
    dict of (k,) arrays
        ``start_s``, ``duration_s``, ``path_mm``, ``chord_mm``,
        ``straightness``, ``plunge``.
    """
    v = np.asarray(view, float)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError("view must be a non-zero vector")
    v = v / n
    t = np.asarray(samples["t_s"], float)
    p = np.asarray(samples["pos_mm"], float).reshape(-1, 3)
    a, b = _runs(drilling_mask(samples))
    keep = [(i, j) for i, j in zip(a, b) if t[j - 1] - t[i] >= min_s]
    out = {k: np.zeros(len(keep)) for k in ("start_s", "duration_s", "path_mm", "chord_mm",
                                           "straightness", "plunge")}
    for q, (i, j) in enumerate(keep):
        seg = p[i:j]
        path = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        chord_v = seg[-1] - seg[0]
        chord = float(np.linalg.norm(chord_v))
        out["start_s"][q] = t[i]
        out["duration_s"][q] = t[j - 1] - t[i]
        out["path_mm"][q] = path
        out["chord_mm"][q] = chord
        out["straightness"][q] = chord / path if path > 0 else 1.0
        out["plunge"][q] = abs(float(chord_v @ v)) / chord if chord > 0 else 0.0
    return out


def stroke_summary(st: dict) -> dict:
    """Counts and means of :func:`strokes` (NaN where there is no stroke)."""
    k = len(st["path_mm"])
    mean = (lambda a: float(np.mean(a))) if k else (lambda a: float("nan"))
    cv = float(np.std(st["path_mm"]) / np.mean(st["path_mm"])) \
        if k and np.mean(st["path_mm"]) > 0 else float("nan")
    return {"strokes": k, "mean_path_mm": mean(st["path_mm"]),
            "mean_duration_s": mean(st["duration_s"]),
            "mean_straightness": mean(st["straightness"]), "mean_plunge": mean(st["plunge"]),
            "consistency_cv": cv}


def _applied_force(samples) -> np.ndarray:
    f = np.asarray(samples["force_n"], float) - np.asarray(samples["vibration_n"], float)
    return np.linalg.norm(f.reshape(-1, 3), axis=1)


def excessive_force_events(samples, max_force_n: float, share: float = EXCESSIVE_SHARE,
                           min_s: float = MIN_EVENT_S) -> dict:
    """Excessive-force events (module docstring).

    Parameters
    ----------
    samples : dict
    max_force_n : float or (n,) float
        The force limit of each step [N] (module docstring).
    share : float
        Threshold as a share of ``max_force_n``, in (0, 1].
    min_s : float
        Shortest event [s].

    Returns
    -------
    dict of (k,) arrays
        ``start_s``, ``duration_s``, ``peak_n``.
    """
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share must lie in (0, 1], got {share}")
    t = np.asarray(samples["t_s"], float)
    lim = np.broadcast_to(np.asarray(max_force_n, float), t.shape)
    if not (np.isfinite(lim).all() and (lim > 0).all()):
        raise ValueError("max_force_n must be finite forces > 0 [N]")
    f = _applied_force(samples)
    a, b = _runs(f >= share * lim)
    keep = [(i, j) for i, j in zip(a, b) if t[j - 1] - t[i] >= min_s]
    return {"start_s": np.array([t[i] for i, _ in keep]),
            "duration_s": np.array([t[j - 1] - t[i] for i, j in keep]),
            "peak_n": np.array([f[i:j].max() for i, j in keep])}


def burr_gaps(samples, clearance, labels, burr_radii_mm) -> np.ndarray:
    """Burr gap [mm] of every sample to each structure (module docstring).

    Parameters
    ----------
    samples : dict
        ``pos_mm`` and ``burr`` (index into ``burr_radii_mm``).
    clearance : Clearance
        Holds every label of ``labels``.
    labels : sequence of int
        Structure labels.
    burr_radii_mm : (n_burrs,) float
        Radius per session burr index [mm].

    Returns
    -------
    (n, k) float64
    """
    p = np.asarray(samples["pos_mm"], float).reshape(-1, 3)
    r = np.asarray(burr_radii_mm, float)[np.asarray(samples["burr"], np.int64)]
    if len(p) == 0 or len(labels) == 0:
        return np.zeros((len(p), len(labels)))
    return clearance.distances(p, [[int(s)] for s in labels]) - r[:, None]


def time_near(samples, gaps, near_mm=NEAR_MM) -> np.ndarray:
    """Drilling time [s] with the burr gap under each threshold.

    Parameters
    ----------
    samples : dict
    gaps : (n, k) float
        :func:`burr_gaps`.
    near_mm : sequence of float
        Thresholds [mm].

    Returns
    -------
    (k, len(near_mm)) float64
        Each sample counts for the interval to the next sample.
    """
    t = np.asarray(samples["t_s"], float)
    dt = np.diff(t, append=t[-1]) if len(t) else t
    drill = drilling_mask(samples)
    out = np.zeros((gaps.shape[1], len(near_mm)))
    for c, thr in enumerate(near_mm):
        out[:, c] = ((gaps < thr) & drill[:, None]).T.astype(float) @ dt
    return out


def drilled_volume(removals, n_labels: int, voxel_mm: float, distance_mm=None,
                   bands_mm=BANDS_MM) -> dict:
    """Drilled volume [mm^3] per structure label and per distance band.

    Parameters
    ----------
    removals : dict
        ``label`` per removed voxel.
    n_labels : int
        Labels 0..n_labels.
    voxel_mm : float
        Voxel edge [mm].
    distance_mm : (n, k) float, optional
        Each removed voxel's distance to ``k`` structures [mm].
    bands_mm : sequence of float
        Band edges [mm]: ``[0, b0), [b0, b1), ..., [b_last, inf)``.

    Returns
    -------
    dict
        ``by_label`` (n_labels + 1,) and, with distances, ``by_band``
        (k, len(bands_mm) + 1).
    """
    v = float(voxel_mm) ** 3
    lab = np.asarray(removals["label"], np.int64)
    out = {"by_label": np.bincount(lab, minlength=n_labels + 1)[:n_labels + 1] * v}
    if distance_mm is not None:
        edges = np.asarray(bands_mm, float)
        d = np.asarray(distance_mm, float).reshape(len(lab), -1)
        band = np.searchsorted(edges, d, side="right")
        out["by_band"] = np.stack([np.bincount(band[:, c], minlength=len(edges) + 1) * v
                                   for c in range(d.shape[1])]).reshape(d.shape[1], -1)
    return out


def burr_stages(samples, burr_names, gaps_critical=None, diameters_mm=None,
                n_stages: int = N_STAGES, near_mm: float = NEAR_BURR_MM) -> dict:
    """Burr choice per stage of the drilling time (module docstring).

    Returns
    -------
    dict
        ``stages``: a list of ``{burr name: share of the stage's drilling
        time}``; with ``gaps_critical`` ((n,) burr gap to the nearest critical
        structure [mm]) and ``diameters_mm`` (per burr index), also
        ``diameter_near_mm`` and ``diameter_far_mm``.
    """
    t = np.asarray(samples["t_s"], float)
    dt = np.diff(t, append=t[-1]) if len(t) else t
    drill = drilling_mask(samples)
    burr = np.asarray(samples["burr"], np.int64)
    clock = np.cumsum(np.where(drill, dt, 0.0))
    total = clock[-1] if len(clock) else 0.0
    stage = np.minimum((clock / total * n_stages).astype(np.int64), n_stages - 1) \
        if total > 0 else np.zeros(len(t), np.int64)
    stages = []
    for s in range(n_stages):
        sel = drill & (stage == s)
        tot = float(dt[sel].sum())
        stages.append({burr_names[b]: float(dt[sel & (burr == b)].sum()) / tot
                       for b in np.unique(burr[sel])} if tot > 0 else {})
    out = {"stages": stages}
    if gaps_critical is not None and diameters_mm is not None:
        d = np.asarray(diameters_mm, float)[burr]
        near = drill & (np.asarray(gaps_critical) < near_mm)
        far = drill & ~near

        def wmean(sel):
            w = dt[sel].sum()
            return float((d[sel] * dt[sel]).sum() / w) if w > 0 else float("nan")
        out["diameter_near_mm"] = wmean(near)
        out["diameter_far_mm"] = wmean(far)
    return out


def injuries_by_structure(session, names) -> dict:
    """``{structure name: {"contacts": n, "injuries": n}}`` over the last epoch."""
    inj = session.injuries
    out = {n: {"contacts": 0, "injuries": 0} for n in names}
    from bonesim.engine import events

    last = final_epoch(session)
    # an event's epoch: the resets published before it
    tis = session.tissue
    resets = np.sort(tis["t_s"][tis["kind"] == events.RESET])
    e_of = np.searchsorted(resets, inj["t_s"], side="right")
    for lab, kind, e in zip(inj["label"], inj["kind"], e_of):
        if e != last or not 1 <= int(lab) <= len(names):
            continue
        key = "injuries" if int(kind) == events.INJURY else "contacts"
        out[names[int(lab) - 1]][key] += 1
    return out


def conduct(session, model=None) -> dict:
    """Every measure of this module for one run, JSON-ready.

    Parameters
    ----------
    session : Session
    model : Model, optional
        The session's model (default ``session.load_model()``); its
        clearance gives the distances.
    """
    h = session.header
    if model is None:
        models = session.burr_models()
        model, burrs = models[0], [m.burr for m in models]
    else:
        burrs = session.recorded_burrs()
    names = [s.name for s in model.structures]
    critical = [k for k, s in enumerate(model.structures, start=1) if s.kind != "bone"]
    smp, rem = last_epoch(session)
    cam = model.case.camera if model.case is not None else None
    view = np.subtract(cam.focal_mm, cam.eye_mm) if cam is not None else (0.0, 0.0, 1.0)
    radii = [b.radius_mm for b in burrs]
    cl = model.clearance
    gaps = burr_gaps(smp, cl, critical, radii) if cl is not None else None
    out = {"strokes": stroke_summary(strokes(smp, view))}
    dev = h["device"]["max_force_n"] or np.inf     # None: the device has no limit
    lim = np.minimum(dev, np.array([b.max_force_n for b in burrs]))[
        np.asarray(smp["burr"], np.int64)]
    if len(lim):
        ev = excessive_force_events(smp, lim)
        out["excessive_force"] = {"events": int(len(ev["start_s"])),
                                  "total_s": float(ev["duration_s"].sum()),
                                  "peak_n": float(ev["peak_n"].max()) if len(ev["peak_n"])
                                  else 0.0}
    voxel = float(h["voxel_mm"])
    dist = None
    if cl is not None and len(rem["ijk"]):
        c = np.asarray(h["origin_mm"], float) + voxel * np.asarray(rem["ijk"], float)
        dist = cl.distances(c, [[s] for s in critical])
    vol = drilled_volume(rem, len(names), voxel, dist)
    out["drilled_mm3"] = {"total": float(vol["by_label"].sum()),
                          "by_structure": {n: float(vol["by_label"][k])
                                           for k, n in enumerate(names, start=1)}}
    if "by_band" in vol:
        edges = [0.0, *BANDS_MM]
        out["drilled_mm3"]["near"] = {
            names[s - 1]: {f"{lo:g}-{hi:g} mm" if hi is not None else f">= {lo:g} mm":
                           float(vol["by_band"][c, q])
                           for q, (lo, hi) in enumerate(zip(edges, [*BANDS_MM, None]))}
            for c, s in enumerate(critical)}
    if gaps is not None:
        tn = time_near(smp, gaps)
        out["time_near_s"] = {names[s - 1]: {f"< {thr:g} mm": float(tn[c, q])
                                             for q, thr in enumerate(NEAR_MM)}
                              for c, s in enumerate(critical)}
    out["burr"] = burr_stages(smp, [b["name"] for b in h["burrs"]],
                              gaps.min(axis=1) if gaps is not None and gaps.size else None,
                              [b.diameter_mm for b in burrs])
    out["contacts"] = injuries_by_structure(session, names)
    return out
