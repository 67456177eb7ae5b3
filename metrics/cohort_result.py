"""What scoring a cohort gives: the record :mod:`metrics.cohort` fills and
:mod:`metrics.report` draws.

A cohort is a folder (or glob) of session files and a participants table
(``participants.csv``: ``id, group, instructor_score`` and optionally
``session`` and ``file``, one row per session; ``group`` is ``expert`` or
``novice``, the score may be empty). Scoring it gives one tidy table, a row
per run, with every scalar metric; the per-run tables the plots need; and
the group statistics of every metric, per participant, with corrections.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["RUN_COLUMNS", "METRIC_COLUMNS", "STATS_COLUMNS", "CohortResult"]

#: Columns that say which run a row is (always present).
RUN_COLUMNS = ("file", "participant", "group", "session", "instructor_score", "case", "error")

#: The scalar metrics of a row, with their units and which direction is
#: better (+1: higher is better, -1: lower, 0: neither). A row of a run that
#: failed to load holds NaN in all of them and its message in ``error``.
METRIC_COLUMNS = {
    "duration_s": ("s", 0),
    "removed_voxels": ("voxels", 0),
    "drilled_mm3": ("mm^3", 0),
    "visible_fraction": ("", +1),
    "nb_score": ("nats", +1),
    "nb_score_per_voxel": ("nats/voxel", +1),
    "force_near_n": ("N", -1),
    "force_close_n": ("N", -1),
    "clamped_share": ("", -1),
    "speed_near_rpm": ("rpm", 0),
    "tool_speed_near_mm_s": ("mm/s", -1),
    "tool_speed_close_mm_s": ("mm/s", -1),
    "exceedances": ("", -1),
    "exceedances_close": ("", -1),
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


#: Columns of :attr:`CohortResult.stats` (:func:`metrics.group_stats.group_statistics`).
STATS_COLUMNS = (
    "metric", "unit", "better", "family", "expert_n", "expert_mean", "expert_sd",
    "novice_n", "novice_mean", "novice_sd", "t", "p_t", "p_t_holm", "p_t_bh", "p_t_adj",
    "correction", "significant", "u", "p_u", "u_method", "d", "d_lo", "d_hi", "d_note",
    "auc", "auc_lo", "auc_hi", "auc_expert_is", "mixed_group_effect", "mixed_group_se",
    "mixed_p_group", "p_mixed_holm", "p_mixed_bh", "p_mixed_adj", "mixed_significant",
    "mixed_session_effect", "mixed_session_se", "mixed_p_session", "mixed_converged",
    "mixed_note", "rho", "p_rho", "r", "p_r")


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
        One row per tested metric, :data:`STATS_COLUMNS`
        (:func:`metrics.group_stats.group_statistics`): per participant by
        default (each participant's mean), the expert and novice ``n, mean,
        sd``, the tests with their Holm, Benjamini-Hochberg and declared
        (``_adj``) corrections within the metric's ``family``, Cohen's d
        (NaN with ``d_note`` when a group has no variance), the AUC of the
        metric as a group classifier, the mixed model's group and session
        effects, and the correlations with the instructor scores.
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
        ``wall_s``, ``participants_file``, ``sessions``, ``stats_s`` (time
        of the statistics step [s]).
    excluded : dict
        Metric -> why it is not tested (design constant, a copy of another
        metric, no values ...).
    design : dict
        The declared design (:meth:`metrics.group_stats.Design.summary`).
    classifiers : dict
        ``nb_score`` and ``nb_score_per_voxel`` -> the leave-one-participant-out
        ROC (:func:`metrics.agreement.roc_auc` of the participants' mean
        scores: ``auc``, ``auc_ci``, ``fpr``, ``tpr`` ...).
    agreement : dict
        Test-retest per primary metric between each participant's first and
        last session: ``icc`` (:func:`metrics.agreement.icc`) and
        ``bland_altman`` (:func:`metrics.agreement.bland_altman`).
    provenance : dict
        :func:`metrics.provenance.provenance`: bonesim version, case and burr
        hashes, participants-file hash, synthesis seed, command line.
    exceedances : dict
        ``file -> metrics.forces.Exceedances`` of every run scored against
        the other participants' expert limits.
    instructors : dict
        With a ratings file (:mod:`metrics.raters`): ``file``, ``sha256``
        and :func:`metrics.raters.instructor_agreement` (``between_raters``,
        ``against``); empty without one.
    """

    table: object
    stats: object
    force_tables: dict = field(default_factory=dict)
    nb_trained_on: dict = field(default_factory=dict)
    structure: str = "chorda_tympani"
    errors: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    excluded: dict = field(default_factory=dict)
    design: dict = field(default_factory=dict)
    classifiers: dict = field(default_factory=dict)
    agreement: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    exceedances: dict = field(default_factory=dict)
    instructors: dict = field(default_factory=dict)
