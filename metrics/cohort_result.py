"""What scoring a cohort gives: the record :mod:`metrics.cohort` fills and
:mod:`metrics.report` draws.

A cohort is a folder (or glob) of session files and a participants table
(``participants.csv``: ``id, group, instructor_score``; ``group`` is
``expert`` or ``novice``, the score may be empty). Scoring it gives one
tidy table, a row per run, with every scalar metric; the per-run tables the
plots need; and the group statistics of every metric.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["RUN_COLUMNS", "METRIC_COLUMNS", "CohortResult"]

#: Columns that say which run a row is (always present).
RUN_COLUMNS = ("file", "participant", "group", "instructor_score", "case", "error")

#: The scalar metrics of a row, with their units and which direction is
#: better (+1: higher is better, -1: lower, 0: neither). A row of a run that
#: failed to load holds NaN in all of them and its message in ``error``.
METRIC_COLUMNS = {
    "duration_s": ("s", 0),
    "removed_voxels": ("voxels", 0),
    "drilled_mm3": ("mm^3", 0),
    "visible_fraction": ("", +1),
    "nb_score": ("nats", +1),
    "force_near_n": ("N", -1),
    "speed_near_rpm": ("rpm", 0),
    "exceedances": ("", -1),
    "exposure_facial_nerve_1mm": ("", 0),
    "exposure_sigmoid_sinus_1mm": ("", 0),
    "exposure_middle_fossa_dura_1mm": ("", 0),
    "strokes": ("", 0),
    "mean_plunge": ("", -1),
    "mean_straightness": ("", +1),
    "stroke_cv": ("", -1),
    "excessive_force_s": ("s", -1),
    "time_near_critical_1mm_s": ("s", -1),
    "injuries": ("", -1),
    "final_dice": ("", +1),
    "final_mean_mm": ("mm", -1),
}


@dataclass
class CohortResult:
    """A scored cohort.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per session file found, in file-name order: the
        :data:`RUN_COLUMNS` and the :data:`METRIC_COLUMNS` (float; NaN where
        a metric does not apply or the run failed). ``nb_score`` is each
        run's leave-one-participant-out Naive Bayes score and
        ``final_*`` its final product against the *other* participants'
        expert runs (never itself).
    stats : pandas.DataFrame
        One row per metric of :data:`METRIC_COLUMNS` that has values in both
        groups: ``metric, unit, better``, the expert and novice ``n, mean,
        sd``, ``t, p_t, u, p_u, u_method, d, d_lo, d_hi`` (from
        :func:`metrics.validity.compare_groups`) and, where instructor
        scores exist, ``rho, p_rho, r, p_r`` (from
        :func:`metrics.validity.correlate`).
    force_tables : dict
        ``file -> metrics.forces.ForceTable`` of every run that loaded, for
        the force-versus-distance plot.
    nb_trained_on : dict
        ``file -> list of files`` that trained its Naive Bayes score.
    structure : str
        The structure of the force tables.
    errors : list of str
        One line per run that failed (also in ``table.error``), and per
        participant of the table with no run, or run with no participant.
    meta : dict
        How it ran: ``scheduler`` (address or "LocalCluster"), ``workers``,
        ``wall_s``, ``participants_file``, ``sessions``.
    """

    table: object
    stats: object
    force_tables: dict = field(default_factory=dict)
    nb_trained_on: dict = field(default_factory=dict)
    structure: str = "chorda_tympani"
    errors: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)
