"""Score a cohort of recorded runs on a Dask cluster (``bonesim metrics cohort``).

A cohort is a folder (or glob, or list) of session files and a participants
table (``id, group, instructor_score`` and optionally ``session`` and
``file``: :mod:`metrics.participants`). :func:`score_cohort` fills a
:class:`metrics.cohort_result.CohortResult`:

Per run, on the cluster
    One Dask task per file reads the session and computes what needs only
    that run: the visible fraction (:func:`metrics.visibility.visibility`),
    the force table near ``structure`` (:func:`metrics.forces.force_vs_distance`)
    with its mean force [N], spindle speed [rpm] and tool speed [mm/s], the
    same within the design's ``close_mm``, the share of its rows at the
    force clamp (``clamped_share``), the share of each skeletonized
    structure's surface under less than 1 mm of bone
    (:func:`metrics.exposure.exposure`), the conduct scalars
    (:func:`metrics.conduct.conduct`), and the drilled set (the voxels
    removed in the run's final epoch) the central steps need, and the
    columns of every per-run row provider (:data:`ROW_PROVIDERS`). A task never
    raises: a file that cannot be read, or is of another case than the
    cohort's (the majority case of the files), gives its one-line message
    instead. Each worker keeps the
    models it rebuilt (per recorded case, burrs and model hash), so a
    cohort of one case rebuilds them once per worker.
Centrally, in the client
    Each run's session (:func:`metrics.participants.assign_sessions`). The
    Naive Bayes score of every run with a group, leave one participant out
    (:func:`metrics.regions.loo_scores`), summed and per voxel (over the
    region's voxels), and of every run without one by a model of all the
    labelled runs; the final product of every run
    against the *other* participants' expert runs (mean Dice and mean
    symmetric distance [mm], :func:`metrics.final_product.compare`); the
    exceedances of every run against limits learned from the *other*
    participants' expert force tables (:func:`metrics.forces.learn_limits`,
    with the experts' closest approach limiting the bins they never reached);
    the group statistics of every metric per participant with the mixed
    model and corrections (:func:`metrics.group_stats.group_statistics`); the
    ROC of the Naive Bayes scores; test-retest agreement of the primary
    metrics (ICC, Bland-Altman); the provenance.

Shed specks (removals of specks shed as dust with a cut-off fragment) are
left out of every per-run metric: visibility, forces, volume, regions.

Runs whose participant is not in the table are scored against the whole
labelled set (group empty) and left out of the group statistics; participants
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
from metrics.assessment import cohort_columns
from metrics.participants import assign_sessions, read_participants
from metrics.run_identity import distinct_runs

__all__ = ["ROW_PROVIDERS", "read_participants", "find_sessions", "score_file",
           "score_cohort", "write_table", "metric_columns", "local_cluster"]

#: Remaining bone [mm] of the exposure columns.
EXPOSURE_MM = 1.0
#: Structures of the ``exposure_*_1mm`` columns.
EXPOSURE_STRUCTURES = ("facial_nerve", "sigmoid_sinus", "middle_fossa_dura")
#: Burr gap [mm] of ``time_near_critical_1mm_s``.
NEAR_MM = 1.0
#: A force row within this share of the clamp is "at the clamp".
CLAMP_RTOL = 1e-3

#: Per-run row providers: extra columns joined to each run's row. An entry
#: is ``(module, function, columns)``: ``module.function(session, models,
#: path) -> dict`` runs in the worker after the built-in metrics (``models``:
#: one engine model per burr) and returns a value per column; ``columns``
#: maps each column to ``(unit, better)`` as :data:`METRIC_COLUMNS` does.
#: Its columns follow the built-in ones in the table and are tested like them.
#: A provider that raises leaves its columns NaN and gives one error line.
#: The final-product assessment (:mod:`metrics.assessment`) is one: its
#: ``assess_*`` columns put each item of the scale beside the metrics, per run
#: and so per participant and session (the learning curves).
ROW_PROVIDERS: tuple = (("metrics.assessment", "cohort_row", cohort_columns()),)


def metric_columns(providers=None) -> dict:
    """The built-in metric columns and every provider's, in table order."""
    out = dict(METRIC_COLUMNS)
    for _mod, _fn, cols in (ROW_PROVIDERS if providers is None else providers):
        out.update(cols)
    return out


# ----------------------------------------------------------------- inputs
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


def one_line(exc) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if type(exc).__name__ == "BonesimError" else f"{type(exc).__name__}: {msg}"


def score_file(path, structure: str = "chorda_tympani", case: str | None = None,
               close_mm: float = 8.0, providers=None) -> dict:
    """The per-run part of the cohort's metrics for one file (one Dask task).

    Parameters
    ----------
    path : path
        A session file.
    structure : str
        Structure of the force table.
    case : str, optional
        The cohort's case; a file of another case is refused.
    close_mm : float
        Distance [mm] of the ``*_close_*`` columns.
    providers : sequence, optional
        Row providers (default :data:`ROW_PROVIDERS`).

    Returns
    -------
    dict
        ``file`` and, for a run that loaded: ``participant``, ``case``,
        ``damage`` (the damage notice or None), ``shape``, ``voxel_mm``,
        ``metrics`` (the per-run columns of
        :data:`metrics.cohort_result.METRIC_COLUMNS`), ``force_table``
        (:class:`metrics.forces.ForceTable` or None) and ``drilled`` (flat
        voxel indices removed in the final epoch: the Naive Bayes region and
        the final product's set), ``start_time``, ``header`` (case and burrs
        with their hashes, bonesim version), ``extra`` (the providers'
        columns) and ``warnings``; for one that did not, ``error`` (one
        line). Never raises.
    """
    path = Path(path)
    try:
        return _score_file(path, structure, case, close_mm,
                           ROW_PROVIDERS if providers is None else providers)
    except Exception as exc:                # one line per failed run, never a crash
        msg = one_line(exc)
        if str(path) not in msg:
            msg = f"{path}: {msg}"
        return {"file": str(path), "error": msg}


def _score_file(path, structure, case, close_mm, providers):
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
    # visible share of the drilled removals (shed specks left out, as everywhere)
    vis = visibility(s, models=models)
    drilled = events.drilled(s.tissue)[np.asarray(s.tissue["kind"]) == events.REMOVED]
    judged = vis.visible[drilled]
    m["visible_fraction"] = float(np.mean(judged == 1)) if len(judged) else nan
    table = None
    if structure in names:
        table = force_vs_distance(s, structure, model=model)
        if len(table):
            m["force_near_n"] = float(np.mean(table.force_n))
            m["speed_near_rpm"] = float(np.mean(table.speed_rpm))
            m["tool_speed_near_mm_s"] = float(np.mean(table.tool_mm_s))
            clamp = min(float(x.max_force_n) for x in models)
            m["clamped_share"] = float(np.mean(table.force_n >= clamp * (1 - CLAMP_RTOL)))
            close = table.distance_mm <= close_mm
            if close.any():
                m["force_close_n"] = float(np.mean(table.force_n[close]))
                m["tool_speed_close_mm_s"] = float(np.mean(table.tool_mm_s[close]))
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
    extra, warn = {}, []
    for mod, fn, cols in providers:
        extra.update({k: nan for k in cols})
        try:
            import importlib

            got = getattr(importlib.import_module(mod), fn)(s, models, path)
            extra.update({k: float(got[k]) for k in cols if k in got})
        except Exception as exc:            # its columns stay NaN; say so
            warn.append(f"{path}: {mod}.{fn}: {one_line(exc)}")
    return {"file": str(path), "participant": str(h.get("participant", "") or ""),
            "case": mine, "damage": damage_notice(s), "shape": tuple(h["shape"]),
            "notes": str(h.get("notes", "") or ""), "start_time": str(h.get("start_time", "")),
            "header": {"bonesim_version": h.get("bonesim_version"), "case": h["case"],
                       "burrs": h["burrs"]},
            "voxel_mm": float(h["voxel_mm"]), "metrics": m, "force_table": table,
            "drilled": drilled_set(s), "extra": extra, "warnings": warn}


# --------------------------------------------------------------- cluster
def local_cluster(workers: int):
    """A Dask ``LocalCluster`` of ``workers`` single-threaded processes on
    127.0.0.1, with no dashboard and the scheduler's own HTTP endpoint on a
    free loopback port (not 8787, which another cluster may hold)."""
    import logging

    from distributed import LocalCluster

    return LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                        dashboard_address=None, host="127.0.0.1",
                        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                        silence_logs=logging.ERROR)


def dask_client(scheduler, workers):
    """``(client, cluster or None, label)``: connect to ``scheduler`` or start a
    local cluster of ``workers`` single-threaded processes."""
    from distributed import Client

    if scheduler:
        try:
            return Client(scheduler, set_as_default=False, timeout="20s"), None, str(scheduler)
        except (OSError, TimeoutError) as exc:
            from bonesim.errors import BonesimError

            raise BonesimError(f"cannot reach the Dask scheduler {scheduler} "
                               f"({' '.join(str(exc).split()) or type(exc).__name__})") from None
    cluster = local_cluster(workers)
    try:
        return Client(cluster, set_as_default=False), cluster, "LocalCluster"
    except Exception:
        cluster.close()
        raise


def _run_tasks(paths, structure, case, scheduler, workers, progress, close_mm, providers):
    from distributed import as_completed

    client, cluster, label = dask_client(scheduler, workers)
    try:
        futs = [client.submit(score_file, str(p), structure, case, close_mm, providers,
                              pure=False) for p in paths]
        where = {f.key: q for q, f in enumerate(futs)}
        out = [None] * len(futs)
        n_workers = len(client.scheduler_info().get("workers", {}))
        for done, fut in enumerate(as_completed(futs, loop=client.loop), start=1):
            q = where[fut.key]
            try:
                out[q] = fut.result()
            except Exception as exc:        # a worker died, the task was lost ...
                out[q] = {"file": str(paths[q]), "error": f"{paths[q]}: {one_line(exc)}"}
            if progress is not None:
                progress(done, len(futs))
        return out, label, n_workers
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _cached_tasks(paths, structure, case, scheduler, workers, progress, close_mm, providers,
                  cache):
    """:func:`_run_tasks` for the runs ``cache`` does not hold; the clean new
    results are kept in it. Returns ``(runs, label, workers, cached)``."""
    if cache is None:
        return (*_run_tasks(paths, structure, case, scheduler, workers, progress, close_mm,
                            providers), 0)
    from metrics.run_cache import RunCache

    rc = RunCache(cache, {"structure": structure, "case": case, "close_mm": close_mm,
                          "providers": [[m, f, sorted(c)] for m, f, c in providers]})
    got = {q: r for q, r in ((q, rc.get(p)) for q, p in enumerate(paths)) if r is not None}
    todo = [p for q, p in enumerate(paths) if q not in got]
    if progress is not None and got:
        progress(len(got), len(paths))
    if todo:
        step = None if progress is None else \
            (lambda done, _n: progress(len(got) + done, len(paths)))
        fresh, label, n_workers = _run_tasks(todo, structure, case, scheduler, workers, step,
                                             close_mm, providers)
    else:
        fresh, label, n_workers = [], "cache", 0
    new = iter(fresh)
    runs = []
    for q, p in enumerate(paths):
        if q in got:
            runs.append(got[q])
        else:
            r = next(new)
            rc.put(p, r)
            runs.append(r)
    return runs, label, n_workers, len(got)


# --------------------------------------------------------------- central
def _nanmean(v) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else math.nan


def _naive_bayes(runs, table, errors, trained_on):
    """Leave-one-participant-out scores of the labelled runs; the others are
    scored by a model of every labelled run. Summed [nats] and per voxel."""
    from metrics.regions import RegionRun, fit_regions, loo_scores

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

    def put(q, score):
        n = len(runs[q]["drilled"])
        table[q]["nb_score"] = float(score)
        table[q]["nb_score_per_voxel"] = float(score) / n if n else math.nan

    for k, q in enumerate(idx):
        put(q, loo.scores[k])
        trained_on[runs[q]["file"]] = [runs[idx[j]]["file"] for j in loo.trained_on[k]]
    others = [q for q, r in enumerate(runs) if "error" not in r and not r.get("group")]
    if others:
        model = fit_regions(rr)
        for q in others:
            if tuple(runs[q]["shape"]) == model.shape:
                put(q, model.score(runs[q]["drilled"]))
                trained_on[runs[q]["file"]] = [runs[j]["file"] for j in idx]


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


def _exceedances(runs, table, errors, close_mm, found):
    """Exceedances of every run against limits of the *other* participants'
    expert runs; the bins without a force limit are limited by the experts'
    closest approach."""
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
            tabs = [runs[e]["force_table"] for e in others]
            try:
                cache[others] = learn_limits(tabs)     # closest_mm: the experts' closest
            except ValueError as exc:
                cache[others] = None
                errors.append(f"exceedances: no limits without {r['participant']!r} ({exc})")
        if cache[others] is not None:
            ex = exceedances(r["force_table"], cache[others])
            found[r["file"]] = ex
            table[q]["exceedances"] = float(len(ex))
            table[q]["exceedances_close"] = float(np.count_nonzero(ex.distance_mm <= close_mm))


def _classifiers(df) -> dict:
    """ROC of the Naive Bayes scores (already leave-one-participant-out) on
    the participants' means."""
    from metrics.agreement import roc_auc
    from metrics.group_stats import participant_means

    out = {}
    for m in ("nb_score", "nb_score_per_voxel"):
        pm = participant_means(df, m)
        e = (pm["group"] == "expert").to_numpy()
        if e.sum() and (~e).sum():
            r = roc_auc(pm["value"].to_numpy(float), e)
            r["unit"] = "participant (mean of their runs)"
            r["validation"] = "leave one participant out"
            out[m] = r
    return out


def _agreement(df, metrics) -> dict:
    """Test-retest of ``metrics``: each participant's first against last session."""
    from metrics.agreement import bland_altman, icc

    out = {}
    d = df[df["group"].isin(["expert", "novice"]) & np.isfinite(df["session"].astype(float))]
    for m in metrics:
        if m not in d:
            continue
        x = d[np.isfinite(d[m].astype(float))].sort_values("session")
        g = x.groupby("participant")
        pairs = g[m].agg(["first", "last", "size"])
        pairs = pairs[pairs["size"] >= 2]
        if len(pairs) < 3:
            continue
        a, b = pairs["first"].to_numpy(float), pairs["last"].to_numpy(float)
        rec = {"participants": int(len(pairs)), "sessions": "first and last"}
        try:
            rec["icc"] = icc(np.column_stack([a, b]))
        except ValueError as exc:
            rec["icc"] = {"note": str(exc)}
        rec["bland_altman"] = bland_altman(b, a)
        out[m] = rec
    return out


def score_cohort(sessions, participants, *, scheduler=None, workers: int = 2,
                 structure: str = "chorda_tympani", progress=None, design=None,
                 command: str | None = None, ratings=None, ratings_against: str = "assess_total",
                 cache=None) -> CohortResult:
    """Score every run of a cohort (module docstring).

    Parameters
    ----------
    sessions : path, str or sequence of path
        A folder (all its ``*.h5``), a glob pattern, or the session files.
    participants : path
        The participants table (:func:`metrics.participants.read_participants`).
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
    design : path or metrics.group_stats.Design, optional
        The statistical design (default ``metrics/design.toml``).
    command : str, optional
        The command line, for the provenance (default ``sys.argv``).
    ratings : path, optional
        Instructors' scores (``participant,session,rater,score``,
        :func:`metrics.raters.read_ratings`): between-rater ICC and the
        simulator's ``ratings_against`` column against them (``instructors``).
    ratings_against : str
        The simulator's column on the raters' scale.
    cache : path, optional
        A folder of per-run results (:class:`metrics.run_cache.RunCache`):
        a run whose file, bonesim version, scoring code and settings are
        unchanged is read from it instead of scored; ``meta["cached"]``
        counts them. Default: every run is scored.

    Returns
    -------
    CohortResult
        As :mod:`metrics.cohort_result` documents it; ``meta`` also holds
        ``case`` (the cohort's), ``damaged`` (files salvaged and scored
        on their readable part), ``central_s`` (wall time of the steps
        after the per-run tasks [s]) and ``stats_s`` (of the statistics).

    Raises
    ------
    BonesimError
        On a bad participants table or design, no session files, or
        ``workers < 1``.
    """
    import pandas as pd

    from bonesim.errors import BonesimError
    from metrics.group_stats import Design, group_statistics, load_design
    from metrics.provenance import provenance

    t0 = time.perf_counter()
    if scheduler is None and int(workers) < 1:
        raise BonesimError(f"workers must be at least 1, got {workers}")
    design = design if isinstance(design, Design) else load_design(design)
    people = read_participants(participants)
    rated = None
    if ratings is not None:                 # a bad file stops before any scoring
        from metrics.raters import read_ratings

        rated = read_ratings(ratings, people)
    paths, repeated, copies = distinct_runs(find_sessions(sessions))   # a copy counts once
    cases = Counter(c for c in map(_peek_case, paths) if c is not None)
    case = min(cases, key=lambda c: (-cases[c], c)) if cases else None
    providers = tuple(ROW_PROVIDERS)
    runs, label, n_workers, cached = _cached_tasks(paths, structure, case, scheduler, workers,
                                                   progress, design.close_mm, providers, cache)
    t_tasks = time.perf_counter()
    columns = metric_columns(providers)

    errors = list(repeated)
    table = []
    seen = set()
    where, bad = assign_sessions(people, runs, str(participants))
    for r in runs:
        row = {"file": r["file"], "participant": None, "group": None, "session": math.nan,
               "instructor_score": math.nan, "case": None, "error": ""}
        row.update({k: math.nan for k in columns})
        if "error" in r:
            row["error"] = r["error"]
            errors.append(r["error"])
        else:
            p = r["participant"]
            row.update(participant=p, case=r["case"], **r["metrics"], **r["extra"])
            errors.extend(r["warnings"])
            if r["damage"]:
                errors.append(r["damage"])
            if p in people:
                seen.add(p)
                r["group"] = people[p]["group"]
                row.update(group=r["group"], **where[r["file"]])
            else:
                r["group"] = None
                errors.append(f"{r['file']}: participant {p!r} is not in {participants}; "
                              "scored against every labelled run, left out of the statistics")
        table.append(row)
    errors.extend(bad)
    for p in people:
        if p not in seen:
            errors.append(f"{participants}: participant {p!r} has no run")

    trained_on, found = {}, {}
    _naive_bayes(runs, table, errors, trained_on)
    _final_product(runs, table)
    _exceedances(runs, table, errors, design.close_mm, found)

    df = pd.DataFrame(table, columns=[*RUN_COLUMNS, *columns])
    for k in (*columns, "session", "instructor_score"):
        df[k] = df[k].astype(float)
    t_stats = time.perf_counter()
    stats, excluded = group_statistics(df, columns, design)
    classifiers = _classifiers(df)
    agreement = _agreement(df, design.primary)
    instructors = {}
    if rated is not None:
        from metrics.provenance import file_sha256
        from metrics.raters import instructor_agreement

        instructors = {"file": str(ratings), "sha256": file_sha256(ratings),
                       **instructor_agreement(rated, df, ratings_against)}
        for u in instructors["against"]["unmatched"]:
            errors.append(f"{ratings}: {u} has instructor scores but no scored run")
    stats_s = time.perf_counter() - t_stats
    headers = [r["header"] for r in runs if "header" in r]
    return CohortResult(
        table=df, stats=stats,
        force_tables={r["file"]: r["force_table"] for r in runs
                      if r.get("force_table") is not None},
        nb_trained_on=trained_on, structure=structure, errors=errors,
        meta={"scheduler": label, "workers": n_workers,
              "wall_s": time.perf_counter() - t0, "participants_file": str(participants),
              "sessions": [str(p) for p in paths], "case": case, "copies": copies,
              "damaged": [r["file"] for r in runs if r.get("damage")],
              # the report flags synthetic test data (bonesim cohort synth says so)
              "synthetic": any("synthetic" in r.get("notes", "").lower() for r in runs),
              "participants": len(people),
              "sessions_per_participant": _sessions_summary(df),
              "central_s": time.perf_counter() - t_tasks, "stats_s": stats_s,
              "cached": cached},
        excluded=excluded, design=design.summary(), classifiers=classifiers,
        agreement=agreement, exceedances=found, instructors=instructors,
        provenance=_with_ratings(provenance(headers, participants, command=command),
                                 instructors))


def _with_ratings(prov: dict, instructors: dict) -> dict:
    """The provenance with the ratings file and its SHA-256 (when given)."""
    if instructors:
        prov = {**prov, "ratings_file": instructors["file"],
                "ratings_sha256": instructors["sha256"]}
    return prov


def _sessions_summary(df) -> dict:
    """Runs per labelled participant: min, max, and how many participants."""
    d = df[df["group"].isin(["expert", "novice"])]
    n = d.groupby("participant").size()
    return {"min": int(n.min()) if len(n) else 0, "max": int(n.max()) if len(n) else 0,
            "participants": int(len(n))}


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
