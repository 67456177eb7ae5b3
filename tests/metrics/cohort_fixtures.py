"""A small scored cohort for the report tests, built serially.

:func:`score_serially` fills a :class:`metrics.cohort_result.CohortResult`
shaped as that module documents, from a folder that
:func:`metrics.synth.synth_cohort` recorded, with the metrics functions
themselves (no Dask): visible fraction, leave-one-participant-out Naive
Bayes score, force near the chorda, a few conduct numbers, and the group
statistics of every metric (:func:`metrics.group_stats.group_statistics`). It is a test helper,
not the cohort runner (that is :mod:`metrics.cohort`).
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

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
    from metrics.group_stats import group_statistics, load_design

    design = load_design()
    stats, excluded = group_statistics(table, METRIC_COLUMNS, design)
    return CohortResult(table=table, stats=stats, force_tables=tables, excluded=excluded,
                        design=design.summary(),
                        nb_trained_on=trained, structure=structure, errors=errors,
                        meta={"scheduler": "serial (tests/metrics/cohort_fixtures.py)",
                              "workers": 1, "wall_s": math.nan,
                              "participants_file": str(folder / "participants.csv"),
                              "sessions": str(folder / "*.h5")})


def extra_row(session, models, path) -> dict:
    """A per-run row provider for the tests: the run's sample count."""
    return {"samples_n": float(len(session.samples["t_s"]))}


def broken_row(session, models, path) -> dict:
    """A row provider that fails."""
    raise RuntimeError("provider exploded")
