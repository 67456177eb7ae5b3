"""Naive Bayes drilled regions: does a run remove the bone an expert removes?

The model (SPEC "Naive Bayes region correctness"; the thesis's section 3.5.3)
treats each voxel of a case as drilled or not, independently, with one
probability per voxel for experts and one for novices. Trained on runs of
both groups, it scores a run by how much more likely an expert was than a
novice to remove what the run removed.

Voxels
------
A run's **drilled region** is the set of voxels its tissue lacked at the end
of the run: the voxels drilled during its *last epoch* (the samples' ``epoch``
column counts case resets; a reset puts the tissue back, so what was drilled
before the last reset is not part of the final region). A run that ends
right after a reset has an empty region. Voxels are named by their flat index
``np.ravel_multi_index(ijk, shape)`` over the case's grid (``header["shape"]``,
voxels along x, y, z). A removal's ``ijk`` is in its body's own frame, which
is the grid's own lattice (a body's voxels never move in the grid), so split
and moved bodies keep their anatomical index. A fragment cut off is not
drilled: its voxels moved to another body (``SPLIT`` events, not removals),
and the specks shed as dust (removals marked ``shed``,
:data:`bonesim.engine.events.REMOVED_SHED`) are left out.

Estimator
---------
With ``n_E`` expert and ``n_N`` novice training runs, ``c_E(v)`` and
``c_N(v)`` of which removed voxel ``v``, and Laplace smoothing ``alpha > 0``
(default :data:`ALPHA` = 1)::

    P_E(v) = (c_E(v) + alpha) / (n_E + 2 alpha)
    P_N(v) = (c_N(v) + alpha) / (n_N + 2 alpha)

(the posterior mean of a Bernoulli rate under a Beta(alpha, alpha) prior;
never 0 or 1). A run with drilled region ``S`` scores::

    score(S) = sum over v in S of [log P_E(v) - log P_N(v)]

in nats: the log-likelihood ratio, expert over novice, of removing each voxel
of ``S``, as the SPEC states it. Voxels the run left are not counted (the
thesis multiplies the probabilities of the removed voxels only). A voxel no
training run removed still counts: ``log((n_N + 2a) / (n_E + 2a))``, zero
when the groups are the same size. Counts are stored sparsely: only voxels
some training run removed.

Evaluation
----------
:func:`loo_scores` scores every run by a model trained without any run of
its participant (leave one participant out), so no score is in-sample, and
records which runs trained each score.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ALPHA", "EXPERT", "NOVICE", "GROUPS", "RegionRun", "RegionModel", "LooScores",
           "final_epoch", "drilled_voxels", "region_run", "fit_regions", "loo_scores"]

#: Default Laplace smoothing: a Beta(1, 1) (uniform) prior on each voxel's rate.
ALPHA = 1.0
#: The two group names (a session header's ``group``; case and blanks ignored).
EXPERT = "expert"
NOVICE = "novice"
GROUPS = (EXPERT, NOVICE)


def _group(name, what: str) -> str:
    g = str(name).strip().lower()
    if g not in GROUPS:
        raise ValueError(f"{what}: group must be {EXPERT!r} or {NOVICE!r}, got {name!r}")
    return g


def _shape(shape) -> tuple:
    try:
        s = tuple(int(x) for x in shape)
    except TypeError:
        raise ValueError(f"shape must be three voxel counts, got {shape!r}") from None
    if len(s) != 3 or min(s) < 1:
        raise ValueError(f"shape must be three positive voxel counts, got {shape!r}")
    return s


def drilled_voxels(ijk, epoch, shape) -> np.ndarray:
    """Flat indices of a run's drilled region (the removals of its last epoch).

    Parameters
    ----------
    ijk : (n, 3) int
        Removed voxels in removal order (voxel index along x, y, z).
    epoch : (n,) int or int
        Each removal's epoch (case resets before it), or the run's final
        epoch as one int when the removals passed are already that epoch's.
        With an array, removals of epochs below its maximum are dropped.
    shape : (3,) int
        The case grid's voxels along x, y, z.

    Returns
    -------
    (m,) int64
        Sorted, unique flat indices ``np.ravel_multi_index(ijk, shape)``.

    Raises
    ------
    ValueError
        If ``ijk`` is not (n, 3), ``epoch`` does not match it, or a voxel lies
        outside ``shape``.
    """
    shape = _shape(shape)
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ValueError(f"ijk must be (n, 3), got shape {ijk.shape}")
    ep = np.asarray(epoch)
    if ep.ndim == 1:
        if len(ep) != len(ijk):
            raise ValueError(f"epoch has {len(ep)} entries for {len(ijk)} removals")
        if len(ep):
            ijk = ijk[ep == ep.max()]
    elif ep.ndim != 0:
        raise ValueError(f"epoch must be an int or (n,), got shape {ep.shape}")
    ijk = ijk.astype(np.int64)
    if len(ijk) and ((ijk < 0).any() or (ijk >= np.array(shape)).any()):
        bad = ijk[((ijk < 0) | (ijk >= np.array(shape))).any(axis=1)][0]
        raise ValueError(f"ijk: voxel {tuple(bad.tolist())} lies outside the grid {shape}")
    flat = np.ravel_multi_index(ijk.T, shape) if len(ijk) else np.zeros(0, np.int64)
    return np.unique(flat.astype(np.int64))


@dataclass(frozen=True)
class RegionRun:
    """One run's drilled region with who drilled it.

    Attributes
    ----------
    voxels : (m,) int64
        Sorted unique flat voxel indices over ``shape`` (:func:`drilled_voxels`).
    shape : (3,) int
        The case grid's voxels along x, y, z.
    group : str
        :data:`EXPERT` or :data:`NOVICE`.
    participant : str
    case : str
        Case name; runs of one model must share it.
    name : str
        A label for reports (the session file, say).
    """

    voxels: np.ndarray
    shape: tuple
    group: str
    participant: str
    case: str = ""
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "shape", _shape(self.shape))
        object.__setattr__(self, "group", _group(self.group, f"run {self.name!r}"))
        v = np.asarray(self.voxels)
        if v.ndim != 1 or (len(v) and not np.issubdtype(v.dtype, np.integer)):
            raise ValueError(f"voxels of run {self.name!r} must be a 1-D array of flat "
                             "indices")
        v = np.unique(v.astype(np.int64))
        if len(v) and (v[0] < 0 or v[-1] >= int(np.prod(self.shape))):
            raise ValueError(f"voxels of run {self.name!r}: flat index outside the grid "
                             f"{self.shape}")
        v.flags.writeable = False
        object.__setattr__(self, "voxels", v)


def final_epoch(session) -> int:
    """The epoch (case resets before it) a run ended in: its last sample's,
    else (no samples) its last removal's, else 0. Every metric of "what the
    run left" reads this epoch's removals."""
    ep = session.samples.get("epoch", np.zeros(0, np.int32))
    if len(ep):
        return int(ep[-1])
    rep = session.removals["epoch"]
    return int(rep.max()) if len(rep) else 0


def region_run(session, *, group: str | None = None, participant: str | None = None
               ) -> RegionRun:
    """A session's drilled region (:class:`RegionRun`).

    Parameters
    ----------
    session : bonesim.session.reader.Session
        Needs ``header`` (``shape``, ``case``, ``group``, ``participant``),
        ``removals`` (``ijk``, ``epoch``) and ``samples["epoch"]``.
    group, participant : str, optional
        Override the header's.

    Notes
    -----
    The final epoch is the last sample's (a reset after the last removal
    leaves an empty region), else the last removal's.
    """
    h = session.header
    rem = session.removals
    last = final_epoch(session)
    # drilled removals only: specks shed as dust with a fragment were not drilled
    shed = np.asarray(rem.get("shed", np.zeros(len(rem["epoch"]), bool)), bool)
    keep = (rem["epoch"] == last) & ~shed
    voxels = drilled_voxels(rem["ijk"][keep], last, h["shape"])
    name = str(getattr(session, "path", "") or "")
    return RegionRun(voxels, tuple(h["shape"]), h.get("group", "") if group is None else group,
                     str(h.get("participant", "") if participant is None else participant),
                     h.get("case", {}).get("name", ""), name)


@dataclass(frozen=True)
class RegionModel:
    """Per-voxel removal probabilities of experts and novices (sparse counts).

    Attributes
    ----------
    shape : (3,) int
        The case grid's voxels along x, y, z.
    alpha : float
        Laplace smoothing.
    n_expert, n_novice : int
        Training runs per group.
    voxels : (k,) int64
        Sorted flat indices of the voxels some training run removed.
    count_expert, count_novice : (k,) int64
        Training runs of each group that removed each of ``voxels``.
    case : str
    """

    shape: tuple
    alpha: float
    n_expert: int
    n_novice: int
    voxels: np.ndarray
    count_expert: np.ndarray
    count_novice: np.ndarray
    case: str = ""

    def counts(self, voxels) -> tuple[np.ndarray, np.ndarray]:
        """``(c_E, c_N)`` for flat voxel indices (0 for voxels nobody removed)."""
        v = np.asarray(voxels, dtype=np.int64).reshape(-1)
        pos = np.searchsorted(self.voxels, v)
        hit = pos < len(self.voxels)
        hit[hit] = self.voxels[pos[hit]] == v[hit]
        ce = np.zeros(len(v), np.int64)
        cn = np.zeros(len(v), np.int64)
        ce[hit] = self.count_expert[pos[hit]]
        cn[hit] = self.count_novice[pos[hit]]
        return ce, cn

    def probabilities(self, voxels) -> tuple[np.ndarray, np.ndarray]:
        """``(P_E(v), P_N(v))`` per flat voxel index (module notes' estimator)."""
        ce, cn = self.counts(voxels)
        a = self.alpha
        return (ce + a) / (self.n_expert + 2 * a), (cn + a) / (self.n_novice + 2 * a)

    def log_ratio(self, voxels) -> np.ndarray:
        """``log P_E(v) - log P_N(v)`` per flat voxel index [nats]."""
        pe, pn = self.probabilities(voxels)
        return np.log(pe) - np.log(pn)

    def score(self, run) -> float:
        """The score of a drilled region [nats]: the sum of :meth:`log_ratio`
        over its voxels.

        Parameters
        ----------
        run : RegionRun or (m,) int
            A run (its grid must be this model's) or its flat voxel indices
            (duplicates count once).

        Raises
        ------
        ValueError
            If ``run`` is on another grid or case.
        """
        if isinstance(run, RegionRun):
            if run.shape != self.shape or (run.case and self.case and run.case != self.case):
                raise ValueError(f"run: {run.name!r} is on case {run.case!r} grid "
                                 f"{run.shape}, the model on {self.case!r} grid {self.shape}")
            v = run.voxels
        else:
            v = np.unique(np.asarray(run, dtype=np.int64).reshape(-1))
        return float(np.sum(self.log_ratio(v)))


def _check_runs(runs) -> list:
    runs = list(runs)
    if not runs:
        raise ValueError("runs: no runs given")
    for q, r in enumerate(runs):
        if not isinstance(r, RegionRun):
            raise ValueError(f"runs: entry {q} is a {type(r).__name__}, not a RegionRun "
                             "(see region_run)")
    shapes = {r.shape for r in runs}
    cases = {r.case for r in runs if r.case}
    if len(shapes) > 1 or len(cases) > 1:
        raise ValueError(f"runs: all runs must be on one case grid, got cases "
                         f"{sorted(cases)} and grids {sorted(shapes)}")
    return runs


def fit_regions(runs, *, alpha: float = ALPHA) -> RegionModel:
    """Train the per-voxel probabilities on runs of both groups.

    Parameters
    ----------
    runs : sequence of RegionRun
        Training runs, all on one case grid, each with its group.
    alpha : float
        Laplace smoothing, > 0 (default :data:`ALPHA`).

    Returns
    -------
    RegionModel

    Raises
    ------
    ValueError
        On no runs, runs of different grids or cases, a non-positive or
        non-finite ``alpha``, or a group without runs.
    """
    runs = _check_runs(runs)
    alpha = float(alpha)
    if not (np.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be a positive number, got {alpha}")
    n = {g: sum(r.group == g for r in runs) for g in GROUPS}
    missing = [g for g in GROUPS if n[g] == 0]
    if missing:
        raise ValueError(f"runs: no {missing[0]} run to train on (runs of "
                         f"{sorted({r.participant for r in runs})})")
    per = {g: [r.voxels for r in runs if r.group == g] for g in GROUPS}
    allv = np.unique(np.concatenate([r.voxels for r in runs]))
    cnt = {}
    for g in GROUPS:
        flat = np.concatenate(per[g])
        c = np.zeros(len(allv), np.int64)
        np.add.at(c, np.searchsorted(allv, flat), 1)
        cnt[g] = c
    return RegionModel(runs[0].shape, alpha, n[EXPERT], n[NOVICE], allv, cnt[EXPERT],
                       cnt[NOVICE], next((r.case for r in runs if r.case), ""))


@dataclass(frozen=True)
class LooScores:
    """Leave-one-participant-out scores.

    Attributes
    ----------
    scores : (n,) float64
        Each run's score [nats] by a model trained without its participant.
    participants : tuple of str
        Each run's participant.
    groups : tuple of str
        Each run's group.
    trained_on : tuple of (k,) int64
        Per run, the indices (into the runs given) of the runs that trained
        the model that scored it.
    names : tuple of str
    """

    scores: np.ndarray
    participants: tuple
    groups: tuple
    trained_on: tuple
    names: tuple = field(default=())


def loo_scores(runs, participants=None, *, alpha: float = ALPHA) -> LooScores:
    """Score each run by a model trained on every other participant's runs.

    All the runs of a participant are held out together and scored by one
    model (:func:`fit_regions`) trained on the rest; no run is ever scored by
    a model that saw any run of its participant.

    Parameters
    ----------
    runs : sequence of RegionRun
        All on one case grid.
    participants : sequence of str, optional
        Each run's participant id (default each run's ``participant``).
    alpha : float
        Laplace smoothing (default :data:`ALPHA`).

    Returns
    -------
    LooScores

    Raises
    ------
    ValueError
        If ``participants`` does not match ``runs`` or names a blank
        participant, if fewer than two participants are given, or if the
        runs left to train a fold lack a group (the message names the
        participant held out).
    """
    runs = _check_runs(runs)
    if participants is None:
        participants = [r.participant for r in runs]
    participants = [str(p) for p in participants]
    if len(participants) != len(runs):
        raise ValueError(f"participants has {len(participants)} entries for {len(runs)} runs")
    if any(not p.strip() for p in participants):
        raise ValueError("participants: every run needs a participant id")
    who = np.array(participants, dtype=object)
    people = list(dict.fromkeys(participants))
    if len(people) < 2:
        raise ValueError(f"participants: leave-one-out needs two participants or more, "
                         f"got {people}")
    scores = np.full(len(runs), np.nan)
    trained = [None] * len(runs)
    for p in people:
        out = np.flatnonzero(who == p)
        train = np.flatnonzero(who != p)
        try:
            model = fit_regions([runs[q] for q in train], alpha=alpha)
        except ValueError as exc:
            raise ValueError(f"participants: holding out {p!r}: {exc}") from None
        for q in out:
            scores[q] = model.score(runs[q])
            trained[q] = train.copy()
    return LooScores(scores, tuple(participants), tuple(r.group for r in runs),
                     tuple(trained), tuple(r.name for r in runs))
