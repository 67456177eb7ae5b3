"""Safe forces: force and speed against the distance to a structure.

After the thesis's section 3.5.2 (SPEC "Safe forces"): at every removal of a
voxel near a sensitive structure (default the chorda tympani, within 30 mm)
the force applied at that haptic step and the burr's speed are recorded
against the distance from the **removed voxel** to the structure (the
thesis sorts the samples by the removed voxel's distance from the nerve).
Samples are binned by distance (2 mm bins), summarized per group with a mean
and a t-distribution confidence interval, and per-bin limits learned from
expert runs flag where a trainee pressed harder or drilled faster than the
experts did.

Definitions
-----------
Row
    One per removed voxel within ``max_distance_mm`` of the structure (a
    step that removes several voxels gives several rows with that step's
    force and speed, each at its own voxel's distance).
Distance [mm]
    From the removed voxel's centre to the structure's voxels: the exact
    Euclidean distance to the union of the structure's voxel boxes on the
    case's source-resolution label map (:class:`bonesim.physics.clearance.Clearance`),
    0 for a voxel inside the structure. The voxel's centre is
    ``origin_mm + voxel_mm * ijk`` in the case's initial frame: the
    anatomical place, which a body split off and moved does not change.
Force [N]
    :data:`FORCES` names the choices; the default ``"applied"`` is the
    magnitude of the force rendered to the hand without the synthesized
    vibration, ``|force_n - vibration_n|`` (the vibration is a display cue,
    not a force the user pushes against on average).
Speed [rpm]
    The spindle speed of the step (``speed_rpm``).
Tool speed [mm/s]
    How fast the burr's centre moved at the step (``tool_mm_s``): the norm of
    :func:`numpy.gradient` of the sampled positions over the sample times
    (central differences). The thesis' velocities near a structure; the
    spindle speed is set by the burr, this one by the hand.
Shed specks
    Removals marked shed (specks shed as dust with a cut-off fragment,
    :data:`bonesim.engine.events.REMOVED_SHED`) were not drilled and give no
    row, as in every cohort metric (visibility, volume, Naive Bayes).
Bins
    Bin ``b`` holds distances in ``[b w, (b + 1) w)`` for width ``w``
    (default :data:`BIN_MM`); the last bin also holds ``max_distance_mm``.
Group statistics
    Per group and bin, the rows of all the group's runs are pooled (as the
    thesis does): mean, sample standard deviation and the
    ``confidence`` interval ``mean +- t_{(1+c)/2, n-1} sd / sqrt(n)``
    (:func:`scipy.stats.t`). Rows of one run are not independent, so the
    interval is narrower than a per-run analysis would give.
Limits
    Per bin, the :data:`LIMIT_PERCENTILE`-th percentile of the pooled expert
    rows (force and speed separately; linear interpolation): a high
    percentile rather than mean + k sd because forces are non-negative and
    skewed. Bins with fewer than :data:`MIN_LIMIT_SAMPLES` expert rows have no
    force limit (NaN); there the closest approach of the expert rows
    (:func:`closest_approach`, kept in the limits as ``closest_mm``) is the
    limit: a row closer to the structure than every expert ever came, in a
    bin without a force limit, is an exceedance of quantity
    ``"approach_mm"`` (value its distance, limit the closest expert
    distance, excess how much closer).
Exceedance
    A row whose force (speed) is above its bin's limit by more than
    :data:`AT_LIMIT_RTOL` of it (a force clamped at the device's maximum
    equals an expert's clamped force up to rounding: that is at the limit,
    not above it); per haptic step and
    quantity only the row with the largest excess is kept (one report per
    moment, not one per voxel removed in it).

The distance, force, bin, over-the-limit, closest-approach and one-per-step
definitions are the simulator's (:mod:`bonesim.physics.force_limits`,
:func:`~bonesim.physics.force_limits.judge`), so that the window's live
warnings and these exceedances are one law. A limits file (``bonesim metrics
limits``) carries the closest approach, so the window flags an approach closer
than any expert's exactly where the cohort's exceedances count one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from bonesim.physics.force_limits import (AT_LIMIT_RTOL, BIN_MM, DEFAULT_FORCE,
                                          DEFAULT_STRUCTURE, FORCES, MAX_DISTANCE_MM,
                                          QUANTITIES, ForceLimits, bin_edges, bin_index,
                                          force_magnitude, judge, structure_label)

__all__ = ["DEFAULT_STRUCTURE", "MAX_DISTANCE_MM", "BIN_MM", "CONFIDENCE", "FORCES",
           "DEFAULT_FORCE", "LIMIT_PERCENTILE", "MIN_LIMIT_SAMPLES", "AT_LIMIT_RTOL", "QUANTITIES",
           "ForceTable", "BinStats", "Limits", "Exceedances", "bin_edges", "bin_index",
           "structure_label", "force_vs_distance", "group_bins", "learn_limits",
           "exceedances", "expert_limits", "tool_speed", "closest_approach"]

#: Confidence level of the per-bin intervals.
CONFIDENCE = 0.95
#: Percentile of the expert rows that is a bin's limit.
LIMIT_PERCENTILE = 95.0
#: Expert rows a bin needs to get a limit.
MIN_LIMIT_SAMPLES = 5
#: Limits learned from expert runs (the live window checks against the same record).
Limits = ForceLimits


# ------------------------------------------------------------------ the table
@dataclass(frozen=True)
class ForceTable:
    """Force and speed at each removal near a structure (one row per voxel).

    Attributes
    ----------
    t_s : (n,) float64
        Step time [s] (haptic-loop clock).
    voxel_mm : (n, 3) float64
        Removed voxel's centre, case's initial frame [mm].
    pos_mm : (n, 3) float64
        Burr centre at the step, case frame [mm].
    distance_mm : (n,) float64
        Voxel to structure [mm].
    force_n : (n,) float64
        Force magnitude at the step [N] (``force``, see :data:`FORCES`).
    speed_rpm : (n,) float64
        Spindle speed at the step [rpm].
    epoch : (n,) int32
        Case resets before the step.
    structure : str
    max_distance_mm : float
    force : str
        Key of :data:`FORCES`.
    group, participant, case, name : str
        From the session header (``name``: the file).
    tool_mm_s : (n,) float64, optional
        Burr centre's speed at the step [mm/s] (NaN where not measured).
    """

    t_s: np.ndarray
    voxel_mm: np.ndarray
    pos_mm: np.ndarray
    distance_mm: np.ndarray
    force_n: np.ndarray
    speed_rpm: np.ndarray
    epoch: np.ndarray
    structure: str = DEFAULT_STRUCTURE
    max_distance_mm: float = MAX_DISTANCE_MM
    force: str = DEFAULT_FORCE
    group: str = ""
    participant: str = ""
    case: str = ""
    name: str = ""
    tool_mm_s: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.t_s)
        if self.tool_mm_s is None:
            object.__setattr__(self, "tool_mm_s", np.full(n, np.nan))
        for col in ("voxel_mm", "pos_mm"):
            a = np.asarray(getattr(self, col), dtype=np.float64).reshape(-1, 3)
            if len(a) != n:
                raise ValueError(f"{col} has {len(a)} rows, t_s {n}")
            object.__setattr__(self, col, a)
        for col, dt in (("t_s", np.float64), ("distance_mm", np.float64),
                        ("force_n", np.float64), ("speed_rpm", np.float64),
                        ("epoch", np.int32), ("tool_mm_s", np.float64)):
            a = np.asarray(getattr(self, col), dtype=dt).reshape(-1)
            if len(a) != n:
                raise ValueError(f"{col} has {len(a)} rows, t_s {n}")
            object.__setattr__(self, col, a)
        if self.force not in FORCES:
            raise ValueError(f"force must be one of {sorted(FORCES)}, got {self.force!r}")

    def __len__(self) -> int:
        return len(self.t_s)


def _distance_field(session, label: int, model, clearance):
    """An object with ``distance(points, [label])`` that holds ``label``."""
    if clearance is not None:
        if label not in clearance.structures:
            raise ValueError(f"clearance: it holds structures {list(clearance.structures)}, "
                             f"not {label}")
        return clearance
    if model is None:
        model = session.load_model()
    if model.clearance is not None and label in model.clearance.structures:
        return model.clearance
    # a structure the model's clearance does not hold (bone, or a model built
    # from arrays): the engine grid's own label map
    from bonesim.physics.clearance import Clearance

    _, lab = model.grid.to_dense()
    return Clearance(lab, model.grid.spacing_mm, model.grid.origin_mm, [label])


def force_vs_distance(session, structure: str = DEFAULT_STRUCTURE, *,
                      max_distance_mm: float = MAX_DISTANCE_MM, force: str = DEFAULT_FORCE,
                      model=None, clearance=None, include_shed: bool = False) -> ForceTable:
    """Force and speed at every removal within ``max_distance_mm`` of ``structure``.

    Parameters
    ----------
    session : bonesim.session.reader.Session
        Uses ``header`` (``structures``, ``voxel_mm``, ``origin_mm``, ``case``,
        ``group``, ``participant``), ``removals`` and ``samples``.
    structure : str
        A structure of the session's case, by name.
    max_distance_mm : float
        Farthest removal recorded [mm].
    force : str
        A key of :data:`FORCES`.
    model : bonesim.engine.model.Model, optional
        The session's model (default rebuilt: ``session.load_model()``); pass
        it to score many runs of one case without rebuilding it each time.
    clearance : Clearance, optional
        Distances to use instead of the model's (it must hold the structure).
    include_shed : bool
        Keep the removals of shed specks too (default: drilled removals only,
        module notes).

    Returns
    -------
    ForceTable
        Rows in removal order.

    Raises
    ------
    ValueError
        On an unknown structure (naming the case's structures), a bad
        ``max_distance_mm`` or ``force``, or a removal without a sample at its
        time.
    """
    d_max = float(max_distance_mm)
    if not (math.isfinite(d_max) and d_max > 0):
        raise ValueError(f"max_distance_mm must be a positive number, got {max_distance_mm!r}")
    if force not in FORCES:
        raise ValueError(f"force must be one of {sorted(FORCES)}, got {force!r}")
    h = session.header
    case = h.get("case", {}).get("name", "")
    label = structure_label(h["structures"], structure, case)
    field = _distance_field(session, label, model, clearance)
    rem = session.removals
    if not include_shed and "shed" in rem:
        drop = np.asarray(rem["shed"], bool)
        rem = {k: (np.asarray(v)[~drop] if np.ndim(v) and len(v) == len(drop) else v)
               for k, v in rem.items()}
    s = session.samples
    t = s["t_s"]
    idx = np.clip(np.searchsorted(t, rem["t_s"]), 0, max(len(t) - 1, 0))
    if len(rem["t_s"]) and (len(t) == 0 or np.any(t[idx] != rem["t_s"])):
        q = int(np.flatnonzero((t[idx] != rem["t_s"]) if len(t) else
                               np.ones(len(idx), bool))[0])
        raise ValueError(f"session: the removal at t = {rem['t_s'][q]} s has no sample at "
                         "its time")
    centre = np.asarray(h["origin_mm"], np.float64) + float(h["voxel_mm"]) * \
        np.asarray(rem["ijk"], np.float64).reshape(-1, 3)
    dist = field.distance(centre, [label]) if len(centre) else np.zeros(0)
    keep = dist <= d_max
    idx = idx[keep]
    return ForceTable(np.asarray(rem["t_s"])[keep], centre[keep], s["pos_mm"][idx], dist[keep],
                      force_magnitude(s, force)[idx], s["speed_rpm"][idx], s["epoch"][idx],
                      structure, d_max, force, str(h.get("group", "")).strip().lower(),
                      str(h.get("participant", "")), case,
                      str(getattr(session, "path", "") or ""), tool_speed(s)[idx])


def tool_speed(samples) -> np.ndarray:
    """Burr centre speed per sample [mm/s] (module notes): ``(n,)`` from
    ``samples["pos_mm"]`` ``(n, 3)`` [mm] and ``samples["t_s"]`` ``(n,)`` [s];
    0 for a single sample; repeated times take their first sample's speed."""
    t = np.asarray(samples["t_s"], np.float64)
    p = np.asarray(samples["pos_mm"], np.float64).reshape(-1, 3)
    u, first = np.unique(t, return_index=True)
    if len(u) < 2:
        return np.zeros(len(t))
    v = np.linalg.norm(np.gradient(p[first], u, axis=0), axis=1)
    return v[np.searchsorted(u, t)] if len(u) < len(t) else v


def closest_approach(expert_tables) -> float:
    """The smallest distance [mm] of any row of ``expert_tables`` (inf
    without rows): the limit of the bins without a force limit."""
    d = [tb.distance_mm for tb in expert_tables if len(tb)]
    return float(np.min(np.concatenate(d))) if d else math.inf


def _check_tables(tables, what: str) -> list:
    tables = list(tables)
    if not tables:
        raise ValueError(f"{what}: no tables given")
    for q, tb in enumerate(tables):
        if not isinstance(tb, ForceTable):
            raise ValueError(f"{what}: entry {q} is a {type(tb).__name__}, not a ForceTable")
    kinds = {(tb.structure, tb.force) for tb in tables}
    if len(kinds) > 1:
        raise ValueError(f"{what}: tables measure different structures or forces "
                         f"{sorted(kinds)}")
    return tables


# ------------------------------------------------------------------ statistics
@dataclass(frozen=True)
class BinStats:
    """Per group and distance bin: counts, means and confidence intervals.

    Attributes
    ----------
    groups : tuple of str
        Row order of every array (sorted).
    edges_mm : (b + 1,) float64
        Bin edges [mm].
    n : (g, b) int64
        Rows per group and bin.
    force_mean, force_sd, force_lo, force_hi : (g, b) float64
        Mean, sample standard deviation and interval bounds of the force [N]
        (NaN: mean without rows; sd and interval with fewer than two).
    speed_mean, speed_sd, speed_lo, speed_hi : (g, b) float64
        The same for the speed [rpm].
    confidence : float
    structure, force : str
    """

    groups: tuple
    edges_mm: np.ndarray
    n: np.ndarray
    force_mean: np.ndarray
    force_sd: np.ndarray
    force_lo: np.ndarray
    force_hi: np.ndarray
    speed_mean: np.ndarray
    speed_sd: np.ndarray
    speed_lo: np.ndarray
    speed_hi: np.ndarray
    confidence: float
    structure: str
    force: str

    @property
    def centers_mm(self) -> np.ndarray:
        """Bin centres [mm], ``(b,)``."""
        return 0.5 * (self.edges_mm[:-1] + self.edges_mm[1:])


def _mean_ci(values, bins, nb, confidence):
    """Per bin: n, mean, sd (ddof 1), interval bounds."""
    n = np.bincount(bins, minlength=nb).astype(np.int64)
    tot = np.bincount(bins, weights=values, minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, tot / np.maximum(n, 1), np.nan)
        dev = values - mean[bins]
        ss = np.bincount(bins, weights=dev * dev, minlength=nb)
        sd = np.where(n > 1, np.sqrt(ss / np.maximum(n - 1, 1)), np.nan)
        tq = stats.t.ppf(0.5 * (1.0 + confidence), np.maximum(n - 1, 1))
        half = np.where(n > 1, tq * sd / np.sqrt(np.maximum(n, 1)), np.nan)
    return n, mean, sd, mean - half, mean + half


def group_bins(tables, groups=None, *, bin_mm: float = BIN_MM,
               max_distance_mm: float | None = None,
               confidence: float = CONFIDENCE) -> BinStats:
    """Per-group mean and confidence interval of force and speed per distance bin.

    Parameters
    ----------
    tables : sequence of ForceTable
        One per run, all of one structure and force definition.
    groups : sequence of str, optional
        Each table's group (default the tables' own ``group``).
    bin_mm : float
        Bin width [mm].
    max_distance_mm : float, optional
        Last bin edge [mm] (default the largest of the tables').
    confidence : float
        Interval level, in (0, 1).

    Returns
    -------
    BinStats

    Raises
    ------
    ValueError
        On no tables, tables of different structures or forces, ``groups``
        not matching the tables or blank, a bad ``bin_mm``,
        ``max_distance_mm`` or ``confidence``.
    """
    tables = _check_tables(tables, "tables")
    c = float(confidence)
    if not 0.0 < c < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    if groups is None:
        groups = [tb.group for tb in tables]
    groups = [str(g).strip().lower() for g in groups]
    if len(groups) != len(tables):
        raise ValueError(f"groups has {len(groups)} entries for {len(tables)} tables")
    if any(not g for g in groups):
        raise ValueError("groups: every table needs a group")
    if max_distance_mm is None:
        max_distance_mm = max(tb.max_distance_mm for tb in tables)
    edges = bin_edges(bin_mm, max_distance_mm)
    nb = len(edges) - 1
    names = tuple(sorted(set(groups)))
    out = {k: np.full((len(names), nb), np.nan) for k in
           ("force_mean", "force_sd", "force_lo", "force_hi",
            "speed_mean", "speed_sd", "speed_lo", "speed_hi")}
    n = np.zeros((len(names), nb), np.int64)
    for gi, g in enumerate(names):
        mine = [tb for tb, gg in zip(tables, groups) if gg == g]
        d = np.concatenate([tb.distance_mm for tb in mine])
        b = bin_index(d, edges)
        ok = b >= 0
        for q in ("force", "speed"):
            col = "force_n" if q == "force" else "speed_rpm"
            v = np.concatenate([getattr(tb, col) for tb in mine])[ok]
            cnt, mean, sd, lo, hi = _mean_ci(v, b[ok], nb, c)
            n[gi] = cnt
            out[f"{q}_mean"][gi], out[f"{q}_sd"][gi] = mean, sd
            out[f"{q}_lo"][gi], out[f"{q}_hi"][gi] = lo, hi
    return BinStats(names, edges, n, confidence=c, structure=tables[0].structure,
                    force=tables[0].force, **out)


# ------------------------------------------------------------------ limits
def learn_limits(expert_tables, *, percentile: float = LIMIT_PERCENTILE,
                 bin_mm: float = BIN_MM, max_distance_mm: float | None = None,
                 min_samples: int = MIN_LIMIT_SAMPLES) -> Limits:
    """Per-bin limits: a high percentile of the pooled expert rows.

    Parameters
    ----------
    expert_tables : sequence of ForceTable
        Expert runs (a table whose ``group`` says novice is refused).
    percentile : float
        In (0, 100].
    bin_mm : float
        Bin width [mm].
    max_distance_mm : float, optional
        Last bin edge [mm] (default the largest of the tables').
    min_samples : int
        Expert rows a bin needs to get a limit (>= 1).

    Returns
    -------
    Limits
        With ``closest_mm`` the experts' closest approach
        (:func:`closest_approach`).

    Raises
    ------
    ValueError
        On no tables, a novice's table, mixed structures or forces, or a
        bad ``percentile``, ``bin_mm``, ``max_distance_mm`` or ``min_samples``.
    """
    tables = _check_tables(expert_tables, "expert_tables")
    for tb in tables:
        if tb.group and tb.group != "expert":
            raise ValueError(f"expert_tables: {tb.name or 'a table'} is a {tb.group!r} run")
    p = float(percentile)
    if not 0.0 < p <= 100.0:
        raise ValueError(f"percentile must lie in (0, 100], got {percentile!r}")
    if int(min_samples) < 1:
        raise ValueError(f"min_samples must be at least 1, got {min_samples!r}")
    if max_distance_mm is None:
        max_distance_mm = max(tb.max_distance_mm for tb in tables)
    edges = bin_edges(bin_mm, max_distance_mm)
    nb = len(edges) - 1
    b = bin_index(np.concatenate([tb.distance_mm for tb in tables]), edges)
    f = np.concatenate([tb.force_n for tb in tables])
    v = np.concatenate([tb.speed_rpm for tb in tables])
    n = np.bincount(b[b >= 0], minlength=nb).astype(np.int64)
    lim_f = np.full(nb, np.nan)
    lim_v = np.full(nb, np.nan)
    for q in np.flatnonzero(n >= int(min_samples)):
        m = b == q
        lim_f[q] = np.percentile(f[m], p)
        lim_v[q] = np.percentile(v[m], p)
    return Limits(edges, lim_f, lim_v, n, p, tables[0].structure, tables[0].force,
                  float(max_distance_mm), case=tables[0].case,
                  source=tuple(tb.name for tb in tables),
                  closest_mm=closest_approach(tables))


# ------------------------------------------------------------------ exceedances
@dataclass(frozen=True)
class Exceedances:
    """Moments a run went above the experts' limits, in time order.

    Attributes
    ----------
    t_s : (m,) float64
        Step time [s].
    pos_mm : (m, 3) float64
        Burr centre, case frame [mm].
    voxel_mm : (m, 3) float64
        The removed voxel's centre [mm] (the row with the largest excess).
    distance_mm : (m,) float64
        Its distance to the structure [mm].
    bin : (m,) int64
        Its distance bin.
    quantity : (m,) str
        ``"force_n"`` [N] or ``"speed_rpm"`` [rpm] (:data:`QUANTITIES`), or
        ``"approach_mm"`` [mm] (closer than any expert, in a bin without a
        force limit).
    value, limit, excess : (m,) float64
        What was applied, the bin's limit, and ``value - limit`` (> 0), in
        the quantity's unit; for ``"approach_mm"`` the row's distance, the
        experts' closest approach and ``limit - value`` (> 0).
    """

    t_s: np.ndarray
    pos_mm: np.ndarray
    voxel_mm: np.ndarray
    distance_mm: np.ndarray
    bin: np.ndarray
    quantity: np.ndarray
    value: np.ndarray
    limit: np.ndarray
    excess: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


def exceedances(session_or_table, limits: Limits, *, model=None,
                clearance=None, closest_mm: float | None = None) -> Exceedances:
    """Where a run's force or speed exceeded the limits of its distance bin.

    Parameters
    ----------
    session_or_table : Session or ForceTable
        A session is first turned into its table (:func:`force_vs_distance`
        with the limits' structure, force and range; ``model`` and
        ``clearance`` are passed on).
    limits : Limits
        From :func:`learn_limits`.
    closest_mm : float, optional
        The experts' closest approach [mm]: rows in a bin without a force
        limit and closer than this are ``"approach_mm"`` exceedances
        (``inf``: none are checked). Default ``limits.closest_mm``, which
        :func:`learn_limits` sets to :func:`closest_approach` of its tables.

    Returns
    -------
    Exceedances
        Per haptic step and quantity, the row with the largest excess
        (:func:`bonesim.physics.force_limits.judge`, the rule the live
        window's warnings use).

    Raises
    ------
    ValueError
        If the table measures another structure or force than the limits.
    """
    if not isinstance(limits, Limits):
        raise ValueError(f"limits must be a Limits (learn_limits), got "
                         f"{type(limits).__name__}")
    tb = session_or_table
    if not isinstance(tb, ForceTable):
        tb = force_vs_distance(tb, limits.structure, max_distance_mm=limits.max_distance_mm,
                               force=limits.force, model=model, clearance=clearance)
    if (tb.structure, tb.force) != (limits.structure, limits.force):
        raise ValueError(f"session_or_table: measures {tb.force} force against "
                         f"{tb.structure!r}, the limits {limits.force} force against "
                         f"{limits.structure!r}")
    if closest_mm is not None:
        limits = replace(limits, closest_mm=float(closest_mm))
    got = judge(tb.t_s, tb.distance_mm, {"force_n": tb.force_n, "speed_rpm": tb.speed_rpm},
                limits)
    rows = got["rows"]
    return Exceedances(tb.t_s[rows], tb.pos_mm[rows], tb.voxel_mm[rows], tb.distance_mm[rows],
                       got["bin"], got["quantity"], got["value"], got["limit"], got["excess"])


def expert_limits(paths, participants=None, *, structure: str = DEFAULT_STRUCTURE,
                  percentile: float = LIMIT_PERCENTILE, min_samples: int = MIN_LIMIT_SAMPLES,
                  force: str = DEFAULT_FORCE) -> Limits:
    """Limits learned from the expert runs among recorded session files.

    Parameters
    ----------
    paths : sequence of path
        Session files of one case.
    participants : dict, optional
        ``id -> {"group", ...}`` (:func:`metrics.cohort.read_participants`);
        a run's group is its participant's. Without it, the group each
        session's header records.
    structure, percentile, min_samples, force
        As :func:`force_vs_distance` and :func:`learn_limits`.

    Returns
    -------
    Limits
        With ``source`` naming the runs that trained them.

    Raises
    ------
    ValueError
        Naming the file: a run of another case, a participant missing from
        the table; or no expert run among ``paths``.
    """
    from bonesim.session.reader import read_session

    tables, model, case = [], None, None
    for p in paths:
        s = read_session(p)
        h = s.header
        who = str(h.get("participant", ""))
        if participants is not None:
            if who not in participants:
                raise ValueError(f"{p}: participant {who!r} is not in the participants table")
            group = participants[who]["group"]
        else:
            group = str(h.get("group", "")).strip().lower()
        if group != "expert":
            continue
        name = h.get("case", {}).get("name", "")
        if case is None:
            case, model = name, s.load_model()
        elif name != case:
            raise ValueError(f"{p}: a run of case {name!r}, not {case!r}")
        tb = force_vs_distance(s, structure, force=force, model=model)
        tables.append(replace(tb, group="expert"))
    if not tables:
        raise ValueError("no expert run among the sessions given")
    return learn_limits(tables, percentile=percentile, min_samples=min_samples)
