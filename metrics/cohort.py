"""Score a cohort of recorded runs on a Dask cluster (``bonesim metrics cohort``).

A cohort is a folder (or glob, or list) of session files and a participants
table (``id, group, instructor_score``). :func:`score_cohort` fills a
:class:`metrics.cohort_result.CohortResult`:

Per run, on the cluster
    One Dask task per file reads the session and computes what needs only
    that run: the visible fraction (:func:`metrics.visibility.visibility`),
    the force table near ``structure`` (:func:`metrics.forces.force_vs_distance`)
    with its mean force [N] and speed [rpm], the share of each skeletonized
    structure's surface under less than 1 mm of bone
    (:func:`metrics.exposure.exposure`), the conduct scalars
    (:func:`metrics.conduct.conduct`), and the drilled set (the voxels
    removed in the run's final epoch) the central steps need. A task never
    raises: a file that cannot be read, or is of another case than the
    cohort's (the majority case of the files), gives its one-line message
    instead. Each worker keeps the
    models it rebuilt (per recorded case, burrs and model hash), so a
    cohort of one case rebuilds them once per worker.
Centrally, in the client
    The Naive Bayes score of every run with a group, leave one participant
    out (:func:`metrics.regions.loo_scores`); the final product of every run
    against the *other* participants' expert runs (mean Dice and mean
    symmetric distance [mm], :func:`metrics.final_product.compare`); the
    exceedances of every run against limits learned from the *other*
    participants' expert force tables (:func:`metrics.forces.learn_limits`);
    and the group statistics of every metric (:func:`metrics.validity.compare_groups`,
    :func:`metrics.validity.correlate` against the instructor scores).

Runs whose participant is not in the table are scored where they can be
(group empty) and left out of everything that needs a group; participants
of the table with no run, and salvaged (damaged) files, each give one line in
``errors`` too. A salvaged file is scored on its readable part (its row has
no ``error``; ``meta["damaged"]`` lists it); one with no readable sample
fails.
"""
from __future__ import annotations

import csv
import glob as _glob
import io
import json
import math
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from metrics.cohort_result import METRIC_COLUMNS, RUN_COLUMNS, CohortResult
from metrics.run_identity import distinct_runs

__all__ = ["read_participants", "find_sessions", "score_file", "score_cohort",
           "write_table"]

#: Remaining bone [mm] of the exposure columns.
EXPOSURE_MM = 1.0
#: Structures of the ``exposure_*_1mm`` columns.
EXPOSURE_STRUCTURES = ("facial_nerve", "sigmoid_sinus", "middle_fossa_dura")
#: Burr gap [mm] of ``time_near_critical_1mm_s``.
NEAR_MM = 1.0

_COLUMNS = ("id", "group", "instructor_score")


# ----------------------------------------------------------------- inputs
def read_participants(path) -> dict:
    """Read and check a participants table.

    Parameters
    ----------
    path : path
        A CSV with a header row naming at least ``id``, ``group`` (``expert``
        or ``novice``, any case) and ``instructor_score`` (a number, or empty).

    Returns
    -------
    dict
        ``id -> {"group": str, "instructor_score": float}`` (NaN for an empty
        score), in file order.

    Raises
    ------
    BonesimError
        Naming the file, line and column: a missing file or column, an empty
        or repeated id, a group other than expert/novice, a score that is not
        a number.
    """
    from bonesim.errors import BonesimError

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise BonesimError(f"{path}: cannot read the participants table "
                           f"({getattr(exc, 'strerror', None) or exc})") from None
    out = {}
    rd = csv.reader(io.StringIO(text, newline=""))
    head = next(rd, None)
    if head is None:
        raise BonesimError(f"{path}: line 1: empty file; expected the columns "
                           f"{', '.join(_COLUMNS)}")
    head = [h.strip().lower() for h in head]
    for c in _COLUMNS:
        if c not in head:
            raise BonesimError(f"{path}: line 1: column {c!r} is missing (the header "
                               f"names {', '.join(repr(h) for h in head)})")
    col = {c: head.index(c) for c in _COLUMNS}
    for row in rd:
        line = rd.line_num
        if not any(x.strip() for x in row):
            continue
        cell = {c: (row[k].strip() if k < len(row) else "") for c, k in col.items()}
        if not cell["id"]:
            raise BonesimError(f"{path}: line {line}, column 'id': empty participant id")
        if cell["id"] in out:
            raise BonesimError(f"{path}: line {line}, column 'id': participant "
                               f"{cell['id']!r} is listed twice")
        g = cell["group"].lower()
        if g not in ("expert", "novice"):
            raise BonesimError(f"{path}: line {line}, column 'group': {cell['group']!r} "
                               "is not 'expert' or 'novice'")
        s = cell["instructor_score"]
        try:
            score = float(s) if s else math.nan
        except ValueError:
            score = None
        if score is None or math.isinf(score):
            raise BonesimError(f"{path}: line {line}, column 'instructor_score': "
                               f"{s!r} is not a number")
        out[cell["id"]] = {"group": g, "instructor_score": score}
    return out


def find_sessions(sessions) -> list:
    """The session files of a cohort, sorted by file name.

    Parameters
    ----------
    sessions : path, str or sequence of path
        A folder (its ``*.h5``), a glob pattern, or the files.

    Returns
    -------
    list of Path

    Raises
    ------
    BonesimError
        If nothing matches.
    """
    from bonesim.errors import BonesimError

    if isinstance(sessions, (str, Path)):
        p = Path(sessions)
        if p.is_dir():
            paths = list(p.glob("*.h5"))
        elif any(ch in str(sessions) for ch in "*?["):
            paths = [Path(x) for x in _glob.glob(str(sessions))]
        else:
            paths = [p]
        what = str(sessions)
    else:
        paths = [Path(x) for x in sessions]
        what = "the list given"
    if not paths:
        raise BonesimError(f"{what}: no session files (*.h5) found")
    return sorted(paths, key=lambda q: (q.name, str(q)))


def _peek_case(path) -> str | None:
    """The case name in a file's header, cheaply (None if unreadable)."""
    try:
        import h5py

        from bonesim.session.salvage import open_session_file

        f, _, _, view = open_session_file(Path(path), h5py)     # salvaged files too
        try:
            with f:
                return str(json.loads(f.attrs["header"])["case"]["name"])
        finally:
            if view is not None:
                view.close()
    except Exception:                       # the task reports the real problem
        return None


# --------------------------------------------------------------- per run
_MODELS: dict = {}


def _models(session):
    """The session's burr models, cached per worker process by what the
    header records (case, burrs, device, oversample, model hashes)."""
    h = session.header
    key = json.dumps([h["case"], h["burrs"], h["device"], h["oversample"],
                      h.get("model_sha256")], sort_keys=True, default=str)
    if key not in _MODELS:
        if len(_MODELS) > 8:
            _MODELS.clear()
        _MODELS[key] = session.burr_models()
    return _MODELS[key]


def _one_line(exc) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if type(exc).__name__ == "BonesimError" else f"{type(exc).__name__}: {msg}"


def score_file(path, structure: str = "chorda_tympani", case: str | None = None) -> dict:
    """The per-run part of the cohort's metrics for one file (one Dask task).

    Parameters
    ----------
    path : path
        A session file.
    structure : str
        Structure of the force table.
    case : str, optional
        The cohort's case; a file of another case is refused.

    Returns
    -------
    dict
        ``file`` and, for a run that loaded: ``participant``, ``case``,
        ``damage`` (the damage notice or None), ``shape``, ``voxel_mm``,
        ``metrics`` (the per-run columns of
        :data:`metrics.cohort_result.METRIC_COLUMNS`), ``force_table``
        (:class:`metrics.forces.ForceTable` or None) and ``drilled`` (flat
        voxel indices removed in the final epoch: the Naive Bayes region and
        the final product's set); for one that did not, ``error`` (one
        line). Never raises.
    """
    path = Path(path)
    try:
        return _score_file(path, structure, case)
    except Exception as exc:                # one line per failed run, never a crash
        msg = _one_line(exc)
        if str(path) not in msg:
            msg = f"{path}: {msg}"
        return {"file": str(path), "error": msg}


def _score_file(path, structure, case):
    from bonesim.engine import events
    from bonesim.session.reader import damage_notice, read_session
    from metrics.conduct import conduct
    from metrics.exposure import exposure
    from metrics.final_product import drilled_set
    from metrics.forces import force_vs_distance
    from metrics.visibility import visibility

    s = read_session(path)
    h = s.header
    mine = h["case"]["name"]
    if case is not None and mine != case:
        return {"file": str(path), "error": f"{path}: case {mine!r} is not the cohort's "
                f"case {case!r}"}
    if s.damage is not None and not len(s.samples["t_s"]):
        return {"file": str(path), "error": f"{damage_notice(s)}; nothing to score"}
    models = _models(s)
    model = models[0]
    names = [st.name for st in model.structures]
    nan = math.nan
    m = {k: nan for k in METRIC_COLUMNS}
    t = s.samples["t_s"]
    m["duration_s"] = float(t[-1] - t[0]) if len(t) else 0.0
    # drilled removals: specks shed as dust with a cut-off fragment are not
    m["removed_voxels"] = float(np.count_nonzero(events.drilled(s.tissue)))
    m["visible_fraction"] = float(visibility(s, models=models).fraction)
    table = None
    if structure in names:
        table = force_vs_distance(s, structure, model=model)
        if len(table):
            m["force_near_n"] = float(np.mean(table.force_n))
            m["speed_near_rpm"] = float(np.mean(table.speed_rpm))
    wanted = [n for n in EXPOSURE_STRUCTURES if n in names]
    for n, e in (exposure(s, wanted, model=model) if wanted else {}).items():
        k = list(e.thresholds_mm).index(EXPOSURE_MM) if EXPOSURE_MM in e.thresholds_mm \
            else None
        if k is not None:
            m[f"exposure_{n}_1mm"] = float(e.fraction[k])
    c = conduct(s, model)
    st = c["strokes"]
    m["strokes"] = float(st["strokes"])
    m["mean_plunge"] = float(st["mean_plunge"])
    m["mean_straightness"] = float(st["mean_straightness"])
    m["stroke_cv"] = float(st["consistency_cv"])
    if "excessive_force" in c:
        m["excessive_force_s"] = float(c["excessive_force"]["total_s"])
    m["drilled_mm3"] = float(c["drilled_mm3"]["total"])
    if "time_near_s" in c:
        key = f"< {NEAR_MM:g} mm"
        m["time_near_critical_1mm_s"] = float(sum(v[key] for v in c["time_near_s"].values()))
    m["injuries"] = float(sum(v["injuries"] for v in c["contacts"].values()))
    return {"file": str(path), "participant": str(h.get("participant", "") or ""),
            "case": mine, "damage": damage_notice(s), "shape": tuple(h["shape"]),
            "notes": str(h.get("notes", "") or ""),
            "voxel_mm": float(h["voxel_mm"]), "metrics": m, "force_table": table,
            "drilled": drilled_set(s)}


# --------------------------------------------------------------- cluster
def _client(scheduler, workers):
    """``(client, cluster or None, label)``: connect to ``scheduler`` or start a
    local cluster of ``workers`` single-threaded processes."""
    import logging

    from distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, set_as_default=False, timeout="20s"), None, str(scheduler)
        except (OSError, TimeoutError) as exc:
            from bonesim.errors import BonesimError

            raise BonesimError(f"cannot reach the Dask scheduler {scheduler} "
                               f"({' '.join(str(exc).split()) or type(exc).__name__})") from None
    cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                           dashboard_address=None, host="127.0.0.1",
                           silence_logs=logging.ERROR)
    try:
        return Client(cluster, set_as_default=False), cluster, "LocalCluster"
    except Exception:
        cluster.close()
        raise


def _run_tasks(paths, structure, case, scheduler, workers, progress):
    from distributed import as_completed

    client, cluster, label = _client(scheduler, workers)
    try:
        futs = [client.submit(score_file, str(p), structure, case, pure=False)
                for p in paths]
        where = {f.key: q for q, f in enumerate(futs)}
        out = [None] * len(futs)
        n_workers = len(client.scheduler_info().get("workers", {}))
        for done, fut in enumerate(as_completed(futs, loop=client.loop), start=1):
            q = where[fut.key]
            try:
                out[q] = fut.result()
            except Exception as exc:        # a worker died, the task was lost ...
                out[q] = {"file": str(paths[q]), "error": f"{paths[q]}: {_one_line(exc)}"}
            if progress is not None:
                progress(done, len(futs))
        return out, label, n_workers
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# --------------------------------------------------------------- central
def _nanmean(v) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else math.nan


def _naive_bayes(runs, table, errors, trained_on):
    from metrics.regions import RegionRun, loo_scores

    idx = [q for q, r in enumerate(runs) if r.get("group")]
    if not idx:
        return
    rr = [RegionRun(runs[q]["drilled"], runs[q]["shape"], runs[q]["group"],
                    runs[q]["participant"], runs[q]["case"], runs[q]["file"]) for q in idx]
    try:
        loo = loo_scores(rr)
    except ValueError as exc:
        errors.append(f"naive bayes: not scored ({exc})")
        return
    for k, q in enumerate(idx):
        table[q]["nb_score"] = float(loo.scores[k])
        trained_on[runs[q]["file"]] = [runs[idx[j]]["file"] for j in loo.trained_on[k]]


def _final_product(runs, table):
    from metrics.final_product import compare

    experts = [q for q, r in enumerate(runs) if r.get("group") == "expert"]
    for q, r in enumerate(runs):
        if "error" in r:
            continue
        res = [compare(r["drilled"], runs[e]["drilled"], r["shape"], r["voxel_mm"])
               for e in experts if runs[e]["participant"] != r["participant"]]
        if res:
            table[q]["final_dice"] = _nanmean([x["dice"] for x in res])
            table[q]["final_mean_mm"] = _nanmean([x["mean_mm"] for x in res])


def _exceedances(runs, table, errors):
    from metrics.forces import exceedances, learn_limits

    experts = [q for q, r in enumerate(runs)
               if r.get("group") == "expert" and r.get("force_table") is not None]
    cache = {}
    for q, r in enumerate(runs):
        if r.get("force_table") is None:
            continue
        others = tuple(e for e in experts if runs[e]["participant"] != r["participant"])
        if not others:
            continue
        if others not in cache:
            try:
                cache[others] = learn_limits([runs[e]["force_table"] for e in others])
            except ValueError as exc:
                cache[others] = None
                errors.append(f"exceedances: no limits without {r['participant']!r} ({exc})")
        if cache[others] is not None:
            table[q]["exceedances"] = float(len(exceedances(r["force_table"], cache[others])))


def _stats(df):
    import pandas as pd

    from metrics.validity import compare_groups, correlate

    rows = []
    g = df["group"]
    score = df["instructor_score"].to_numpy(float)
    for name, (unit, better) in METRIC_COLUMNS.items():
        v = df[name].to_numpy(float)
        a = v[(g == "expert").to_numpy() & np.isfinite(v)]
        b = v[(g == "novice").to_numpy() & np.isfinite(v)]
        if len(a) < 2 or len(b) < 2:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                r = compare_groups(a, b)
            except ValueError:
                continue
            row = {"metric": name, "unit": unit, "better": better}
            for grp in ("expert", "novice"):
                for k in ("n", "mean", "sd"):
                    row[f"{grp}_{k}"] = r[grp][k]
            row.update(t=r["t"], p_t=r["p_t"], u=r["u"], p_u=r["p_u"],
                       u_method=r["u_method"], d=r["d"], d_lo=r["d_ci"][0],
                       d_hi=r["d_ci"][1])
            ok = np.isfinite(v) & np.isfinite(score) & g.isin(["expert", "novice"]).to_numpy()
            c = None
            if ok.sum() >= 3:
                try:
                    c = correlate(v[ok], score[ok])
                except ValueError:
                    c = None
            for k in ("rho", "p_rho", "r", "p_r"):
                row[k] = c[k] if c else math.nan
        rows.append(row)
    cols = ["metric", "unit", "better", "expert_n", "expert_mean", "expert_sd", "novice_n",
            "novice_mean", "novice_sd", "t", "p_t", "u", "p_u", "u_method", "d", "d_lo",
            "d_hi", "rho", "p_rho", "r", "p_r"]
    return pd.DataFrame(rows, columns=cols)


def score_cohort(sessions, participants, *, scheduler=None, workers: int = 2,
                 structure: str = "chorda_tympani", progress=None) -> CohortResult:
    """Score every run of a cohort (module docstring).

    Parameters
    ----------
    sessions : path, str or sequence of path
        A folder (all its ``*.h5``), a glob pattern, or the session files.
    participants : path
        The participants table (:func:`read_participants`).
    scheduler : str, optional
        Address of a running Dask scheduler to use (left running). Default:
        a ``LocalCluster`` of ``workers`` processes on 127.0.0.1, no
        dashboard, closed at the end.
    workers : int
        Worker processes of the local cluster (one thread each).
    structure : str
        Structure of the force tables and ``force_near_n``.
    progress : callable, optional
        Called with ``(done, total)`` as the per-run tasks finish.

    Returns
    -------
    CohortResult
        As :mod:`metrics.cohort_result` documents it; ``meta`` also holds
        ``case`` (the cohort's), ``damaged`` (files salvaged and scored
        on their readable part) and ``central_s`` (wall time of the steps
        after the per-run tasks [s]).

    Raises
    ------
    BonesimError
        On a bad participants table, no session files, or ``workers < 1``.
    """
    import pandas as pd

    from bonesim.errors import BonesimError

    t0 = time.perf_counter()
    if scheduler is None and int(workers) < 1:
        raise BonesimError(f"workers must be at least 1, got {workers}")
    people = read_participants(participants)
    paths, repeated, copies = distinct_runs(find_sessions(sessions))   # a copy counts once
    cases = Counter(c for c in map(_peek_case, paths) if c is not None)
    case = min(cases, key=lambda c: (-cases[c], c)) if cases else None
    runs, label, n_workers = _run_tasks(paths, structure, case, scheduler, workers, progress)
    t_tasks = time.perf_counter()

    errors = list(repeated)
    table = []
    seen = set()
    for r in runs:
        row = {"file": r["file"], "participant": None, "group": None,
               "instructor_score": math.nan, "case": None, "error": ""}
        row.update({k: math.nan for k in METRIC_COLUMNS})
        if "error" in r:
            row["error"] = r["error"]
            errors.append(r["error"])
        else:
            p = r["participant"]
            row.update(participant=p, case=r["case"], **r["metrics"])
            if r["damage"]:
                errors.append(r["damage"])
            if p in people:
                seen.add(p)
                r["group"] = people[p]["group"]
                row.update(group=r["group"], instructor_score=people[p]["instructor_score"])
            else:
                r["group"] = None
                errors.append(f"{r['file']}: participant {p!r} is not in {participants}")
        table.append(row)
    for p in people:
        if p not in seen:
            errors.append(f"{participants}: participant {p!r} has no run")

    trained_on = {}
    _naive_bayes(runs, table, errors, trained_on)
    _final_product(runs, table)
    _exceedances(runs, table, errors)

    df = pd.DataFrame(table, columns=[*RUN_COLUMNS, *METRIC_COLUMNS])
    for k in METRIC_COLUMNS:
        df[k] = df[k].astype(float)
    df["instructor_score"] = df["instructor_score"].astype(float)
    return CohortResult(
        table=df, stats=_stats(df),
        force_tables={r["file"]: r["force_table"] for r in runs
                      if r.get("force_table") is not None},
        nb_trained_on=trained_on, structure=structure, errors=errors,
        meta={"scheduler": label, "workers": n_workers,
              "wall_s": time.perf_counter() - t0, "participants_file": str(participants),
              "sessions": [str(p) for p in paths], "case": case, "copies": copies,
              "damaged": [r["file"] for r in runs if r.get("damage")],
              # the report flags synthetic test data (bonesim cohort synth says so)
              "synthetic": any("synthetic" in r.get("notes", "").lower() for r in runs),
              "central_s": time.perf_counter() - t_tasks})


def write_table(result: CohortResult, path) -> Path:
    """Write the cohort's table, by suffix: ``.parquet`` (pyarrow) or ``.csv``.

    Parameters
    ----------
    result : CohortResult
    path : path

    Returns
    -------
    Path

    Raises
    ------
    BonesimError
        On another suffix.
    """
    from bonesim.errors import BonesimError

    path = Path(path)
    suf = path.suffix.lower()
    if suf == ".parquet":
        result.table.to_parquet(path, engine="pyarrow", index=False)
    elif suf == ".csv":
        result.table.to_csv(path, index=False)
    else:
        raise BonesimError(f"{path}: the table is written as .parquet or .csv, not "
                           f"{suf or 'a file without suffix'!r}")
    return path
