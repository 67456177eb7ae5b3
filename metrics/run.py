"""Every metric of one recorded run (``bonesim metrics run FILE.h5``).

:func:`run_metrics` reads a session once, rebuilds its case once, and
gathers, JSON-ready:

``run``
    Who, which case, how long, how much was removed, whether the file was
    damaged (the metrics then cover its readable part, and say so).
``visibility``
    :func:`metrics.visibility.visibility` (recomputed from the file, with the
    count of live verdicts it disagrees with).
``forces``
    :func:`metrics.forces.force_vs_distance` to the chosen structure
    (default the chorda tympani), binned by 2 mm: rows, mean force and
    speed per bin.
``exposure``
    :func:`metrics.exposure.exposure`: the share of each chosen structure's
    surface left under less than 1 mm and 0.5 mm of bone.
``conduct``
    :func:`metrics.conduct.conduct`: strokes, excessive force, time near and
    contacts with each structure, drilled volume, burrs.
``final_product`` (with expert runs)
    :func:`metrics.final_product.compare_to_experts`.
``exceedances`` (with expert runs)
    Where this run's force or speed went above the per-bin limits learned
    from the expert runs' force tables (:func:`metrics.forces.learn_limits`,
    :func:`metrics.forces.exceedances`): how many, and the
    :data:`WORST_SHOWN` largest by excess with time [s], burr position [mm],
    distance [mm], value, limit and excess.
``assessment``
    :func:`metrics.assessment.assess_session`: the final product item by
    item (score, measurement, advice), with ``checklist``, the resident's
    lines.
``alignment`` (with an expert run for the force profile)
    :func:`metrics.alignment.align_sessions` of this run's force against
    the expert's, summarized.

The Naive Bayes region score needs training runs of both groups and lives
with the cohort (:mod:`metrics.regions`).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["WORST_SHOWN", "run_metrics"]

#: Exceedances listed one by one (the largest excesses).
WORST_SHOWN = 5


def _clean(x):
    """JSON-ready: numpy scalars to Python, NaN to None."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (np.floating, float)):
        return None if math.isnan(x) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


def _forces(session, structure, model, tab=None):
    from metrics.forces import bin_edges, bin_index, force_vs_distance

    tab = force_vs_distance(session, structure, model=model) if tab is None else tab
    edges = bin_edges()
    b = bin_index(tab.distance_mm, edges)
    bins = []
    for q in range(len(edges) - 1):
        sel = b == q
        if sel.any():
            bins.append({"from_mm": float(edges[q]), "to_mm": float(edges[q + 1]),
                         "rows": int(sel.sum()), "mean_force_n": float(tab.force_n[sel].mean()),
                         "mean_speed_rpm": float(tab.speed_rpm[sel].mean())})
    return {"structure": structure, "rows": len(tab), "force": tab.force,
            "mean_force_n": float(tab.force_n.mean()) if len(tab) else float("nan"),
            "bins": bins}


def _exceedances(run_table, expert_tables):
    from metrics.forces import exceedances, learn_limits

    lim = learn_limits(expert_tables)
    ex = exceedances(run_table, lim)
    out = {"structure": lim.structure, "percentile": lim.percentile,
           "limited_bins": int(np.count_nonzero(~np.isnan(lim.force_n))),
           "count": {q: int(np.count_nonzero(ex.quantity == q))
                     for q in ("force_n", "speed_rpm", "approach_mm")},
           "closest_mm": float(lim.closest_mm) if np.isfinite(lim.closest_mm) else None,
           "worst": []}
    for q in np.argsort(-ex.excess, kind="stable")[:WORST_SHOWN]:
        out["worst"].append({"t_s": float(ex.t_s[q]), "pos_mm": ex.pos_mm[q].tolist(),
                             "distance_mm": float(ex.distance_mm[q]),
                             "quantity": str(ex.quantity[q]), "value": float(ex.value[q]),
                             "limit": float(ex.limit[q]), "excess": float(ex.excess[q])})
    return out


def run_metrics(session, *, experts=(), force_profile=None, structure: str | None = None,
                exposure_structures=None) -> dict:
    """All metrics of one run (module docstring).

    Parameters
    ----------
    session : Session or path
        The run (a path is read with :func:`bonesim.session.reader.read_session`).
    experts : sequence of Session or path
        Expert runs of the same case for the final product.
    force_profile : Session or path, optional
        An expert run whose force is the target profile for the alignment.
    structure : str, optional
        Structure of the force-versus-distance table (default
        :data:`metrics.forces.DEFAULT_STRUCTURE`).
    exposure_structures : sequence of str, optional
        Default :data:`metrics.exposure.DEFAULT_STRUCTURES`, those the case has.

    Returns
    -------
    dict
        JSON-ready (NaN as None).
    """
    from bonesim.engine import events
    from bonesim.session.reader import read_session
    from metrics.conduct import conduct
    from metrics.exposure import DEFAULT_STRUCTURES, exposure
    from metrics.forces import DEFAULT_STRUCTURE
    from metrics.visibility import visibility

    def load(s):
        return read_session(s) if not hasattr(s, "header") else s

    s = load(session)
    models = s.burr_models()
    model = models[0]
    names = [st.name for st in model.structures]
    h = s.header
    rem = s.tissue["kind"] == events.REMOVED
    out = {"run": {"file": str(getattr(s, "path", "")), "participant": h.get("participant", ""),
                   "case": h["case"]["name"], "burrs": [b["name"] for b in h["burrs"]],
                   "duration_s": float(s.samples["t_s"][-1] - s.samples["t_s"][0])
                   if len(s.samples["t_s"]) else 0.0,
                   "removed_voxels": int(rem.sum()),
                   # of which shed as dust with a cut-off fragment, not drilled
                   "shed_voxels": int(np.count_nonzero(rem & ~events.drilled(s.tissue))),
                   "resets": int(np.count_nonzero(s.tissue["kind"] == events.RESET)),
                   "damaged": getattr(s, "damage", None) is not None}}
    out["visibility"] = visibility(s, models=models).summary()
    structure = DEFAULT_STRUCTURE if structure is None else structure
    run_table = None
    if structure in names:
        from metrics.forces import force_vs_distance

        run_table = force_vs_distance(s, structure, model=model)
        out["forces"] = _forces(s, structure, model, run_table)
    else:
        out["forces"] = {"structure": structure, "skipped": f"case {model.name!r} has no "
                         f"structure {structure!r}"}
    wanted = [n for n in DEFAULT_STRUCTURES if n in names] if exposure_structures is None \
        else list(exposure_structures)
    ex = exposure(s, wanted, model=model) if wanted else {}
    out["exposure"] = {n: {"surface_voxels": e.surface,
                           **{f"under_{t:g}_mm": f for t, f in zip(e.thresholds_mm, e.fraction)}}
                       for n, e in ex.items()}
    out["conduct"] = conduct(s, model)
    if experts:
        from metrics.final_product import compare_to_experts

        panel = [load(e) for e in experts]
        out["final_product"] = compare_to_experts(s, panel, model=model)
        if run_table is not None:
            from metrics.forces import force_vs_distance

            out["exceedances"] = _exceedances(
                run_table, [force_vs_distance(e, structure, model=model) for e in panel])
    from metrics.assessment import assess_session, checklist

    a = assess_session(s, model=model)
    out["assessment"] = {**a.as_dict(), "checklist": checklist(a)}
    if force_profile is not None:
        from metrics.alignment import align_sessions

        out["alignment"] = align_sessions(load(force_profile), s).summary()
    return _clean(out)
