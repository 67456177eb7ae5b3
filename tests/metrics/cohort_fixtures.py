"""A small scored cohort for the report tests, built serially.

:func:`score_serially` fills a :class:`metrics.cohort_result.CohortResult`
shaped as that module documents, from a folder that
:func:`metrics.synth.synth_cohort` recorded, with the metrics functions
themselves (no Dask): visible fraction, leave-one-participant-out Naive
Bayes score, force near the chorda, a few conduct numbers, and the group
statistics of every metric with values in both groups. It is a test helper,
not the cohort runner (that is :mod:`metrics.cohort`).
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pandas as pd

from metrics.cohort_result import METRIC_COLUMNS, RUN_COLUMNS, CohortResult

#: Removals this close to the structure count as "near" [mm].
NEAR_MM = 10.0


def _participants(folder: Path) -> dict:
    with open(folder / "participants.csv", newline="") as f:
        return {r["id"]: r for r in csv.DictReader(f)}


def _score(s):
    try:
        return float(s)
    except (TypeError, ValueError):
        return math.nan


def score_serially(folder, *, structure: str = "chorda_tympani") -> CohortResult:
    """Score every ``*.h5`` of ``folder`` against its ``participants.csv``.

    Returns
    -------
    CohortResult
        ``meta`` says it was scored serially by this helper.
    """
    from bonesim.session.reader import read_session
    from metrics.forces import force_vs_distance
    from metrics.regions import loo_scores, region_run
    from metrics.validity import compare_groups, correlate
    from metrics.visibility import visible_fraction

    folder = Path(folder)
    people = _participants(folder)
    rows, tables, regions, errors, notes = [], {}, [], [], []
    files = sorted(folder.glob("*.h5"))
    for path in files:
        s = read_session(path)
        h = s.header
        pid = str(h.get("participant", ""))
        who = people.get(pid, {})
        group = who.get("group", "")
        notes.append(str(h.get("notes", "")))
        row = {"file": str(path), "participant": pid, "group": group,
               "instructor_score": _score(who.get("instructor_score")),
               "case": h["case"]["name"], "error": ""}
        row.update({m: math.nan for m in METRIC_COLUMNS})
        t = s.samples["t_s"]
        row["duration_s"] = float(t[-1] - t[0]) if len(t) else math.nan
        row["removed_voxels"] = float(len(s.removals["t_s"]))
        models = s.burr_models()
        row["visible_fraction"] = visible_fraction(s, models=models)
        tab = force_vs_distance(s, structure, model=models[0])
        tables[str(path)] = tab
        near = tab.force_n[tab.distance_mm <= NEAR_MM]
        row["force_near_n"] = float(near.mean()) if len(near) else math.nan
        row["speed_near_rpm"] = float(tab.speed_rpm[tab.distance_mm <= NEAR_MM].mean()) \
            if len(near) else math.nan
        regions.append(region_run(s, group=group, participant=pid))
        rows.append(row)
    for pid in sorted(set(people) - {r["participant"] for r in rows}):
        errors.append(f"participant {pid}: no run found")
    loo = loo_scores(regions)
    trained = {}
    for q, row in enumerate(rows):
        row["nb_score"] = float(loo.scores[q])
        trained[row["file"]] = [rows[k]["file"] for k in loo.trained_on[q]]
    table = pd.DataFrame(rows, columns=list(RUN_COLUMNS) + list(METRIC_COLUMNS))
    table["notes"] = notes
    stats = []
    for m, (unit, better) in METRIC_COLUMNS.items():
        e = table.loc[table.group == "expert", m].dropna().to_numpy(float)
        n = table.loc[table.group == "novice", m].dropna().to_numpy(float)
        if len(e) < 2 or len(n) < 2:
            continue
        c = compare_groups(e, n)
        rec = {"metric": m, "unit": unit, "better": better}
        for g in ("expert", "novice"):
            for k in ("n", "mean", "sd"):
                rec[f"{g}_{k}"] = c[g][k]
        rec.update({k: c[k] for k in ("t", "p_t", "u", "p_u", "u_method", "d")})
        rec["d_lo"], rec["d_hi"] = c["d_ci"]
        ok = table[[m, "instructor_score"]].dropna()
        if len(ok) >= 3 and np.ptp(ok[m].to_numpy(float)) > 0:
            r = correlate(ok[m], ok["instructor_score"])
            rec.update({k: r[k] for k in ("rho", "p_rho", "r", "p_r")})
        else:
            rec.update({k: math.nan for k in ("rho", "p_rho", "r", "p_r")})
        stats.append(rec)
    return CohortResult(table=table, stats=pd.DataFrame(stats), force_tables=tables,
                        nb_trained_on=trained, structure=structure, errors=errors,
                        meta={"scheduler": "serial (tests/metrics/cohort_fixtures.py)",
                              "workers": 1, "wall_s": math.nan,
                              "participants_file": str(folder / "participants.csv"),
                              "sessions": str(folder / "*.h5")})
