"""Construct-validity statistics: do the metrics tell experts from novices,
and do they follow the instructors' scores?

The reference studies report a two-tailed t-test and a Mann-Whitney U test
between groups and a correlation with instructor scores (``SPEC.md``,
"Construct validity"). Everything here is :mod:`scipy.stats` plus the
textbook formulas for effect sizes, written out and tested against them
(pingouin offers the same on top of pandas, statsmodels and scikit-learn,
several hundred megabytes this package does not otherwise need).

Group comparison (:func:`compare_groups`)
    Per group ``n``, mean, sd; Student's two-sample t-test (equal
    variances, as the reference studies) and Welch's; the Mann-Whitney U
    test, exact when there are no ties and both groups hold at most
    :data:`EXACT_MAX` values (else the normal approximation with tie
    correction, and the result says which); Cohen's ``d`` (pooled sd) with
    its ``confidence`` interval from the noncentral t distribution, Hedges'
    ``g`` (small-sample corrected), and the rank-biserial correlation
    ``1 - 2 U / (n1 n2)``.
Correlation (:func:`correlate`)
    Spearman's rho and Pearson's R with their two-tailed p-values and
    ``confidence`` intervals from Fisher's z (standard error
    ``1 / sqrt(n - 3)`` for R, ``sqrt(1.06 / (n - 3))`` for rho, after
    Fieller, Hartley and Pearson).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats

__all__ = ["CONFIDENCE", "EXACT_MAX", "compare_groups", "correlate", "cohens_d_ci"]

#: Confidence level of the intervals.
CONFIDENCE = 0.95
#: Largest group for the exact Mann-Whitney distribution.
EXACT_MAX = 50


def _values(a, name) -> np.ndarray:
    v = np.asarray(a, dtype=np.float64).reshape(-1)
    if not np.isfinite(v).all():
        raise ValueError(f"{name}: values must be finite")
    return v


def cohens_d_ci(d: float, n1: int, n2: int, confidence: float = CONFIDENCE):
    """Confidence interval of Cohen's d by inverting the noncentral t.

    ``t = d sqrt(n1 n2 / (n1 + n2))`` follows a noncentral t with
    ``n1 + n2 - 2`` degrees of freedom and noncentrality ``delta sqrt(n1 n2
    / (n1 + n2))``; the bounds are the ``delta`` whose distributions put ``t``
    at the ``(1 +- confidence) / 2`` quantiles.
    """
    df = n1 + n2 - 2
    k = math.sqrt(n1 * n2 / (n1 + n2))
    t = d * k
    alpha = 1.0 - confidence

    def cdf(nc):                     # decreasing in nc; scipy gives NaN deep in a tail
        v = stats.nct.cdf(t, df, nc)
        return (0.0 if nc > t else 1.0) if math.isnan(v) else v

    def bound(q):
        lo, hi = t - 10.0 - abs(t), t + 10.0 + abs(t)
        return optimize.brentq(lambda nc: cdf(nc) - q, lo, hi) / k

    return bound(1.0 - alpha / 2.0), bound(alpha / 2.0)


def compare_groups(a, b, *, names=("expert", "novice"), confidence: float = CONFIDENCE) -> dict:
    """Two groups' values of one metric (module docstring).

    Parameters
    ----------
    a, b : (n,) float
        The metric in each group (e.g. experts, novices), at least 2 each.
    names : (str, str)
    confidence : float
        Of the intervals, in (0, 1).

    Returns
    -------
    dict
        JSON-ready: per-group ``n, mean, sd``; ``t``, ``p_t``, ``df``,
        ``welch_t``, ``p_welch``; ``u``, ``p_u``, ``u_method``; ``d``,
        ``d_ci``, ``g``, ``rank_biserial``; ``d``, ``d_ci`` and ``g`` are NaN,
        and ``d_note`` says why, when a group has no variance (Cohen's d of
        a metric constant within a group is not a finite effect size).
    """
    a, b = _values(a, names[0]), _values(b, names[1])
    if len(a) < 2 or len(b) < 2:
        raise ValueError(f"each group needs at least 2 values, got {len(a)} and {len(b)}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    n1, n2 = len(a), len(b)
    t = stats.ttest_ind(a, b)
    w = stats.ttest_ind(a, b, equal_var=False)
    ties = len(np.unique(np.concatenate([a, b]))) < n1 + n2
    exact = not ties and max(n1, n2) <= EXACT_MAX
    u = stats.mannwhitneyu(a, b, alternative="two-sided",
                           method="exact" if exact else "asymptotic")
    sp = math.sqrt(((n1 - 1) * a.var(ddof=1) + (n2 - 1) * b.var(ddof=1)) / (n1 + n2 - 2))
    flat = [nm for nm, v in zip(names, (a, b)) if np.ptp(v) == 0]
    if flat:                     # a standardized difference needs spread in both groups
        d = lo = hi = math.nan
        note = (f"undefined: no variance within the {' and the '.join(flat)} group"
                f"{'s' if len(flat) > 1 else ''}")
    else:
        d = (a.mean() - b.mean()) / sp
        lo, hi = cohens_d_ci(d, n1, n2, confidence)
        note = ""
    j = 1.0 - 3.0 / (4.0 * (n1 + n2) - 9.0)          # Hedges' small-sample correction
    return {names[0]: {"n": n1, "mean": float(a.mean()), "sd": float(a.std(ddof=1))},
            names[1]: {"n": n2, "mean": float(b.mean()), "sd": float(b.std(ddof=1))},
            "t": float(t.statistic), "p_t": float(t.pvalue), "df": n1 + n2 - 2,
            "welch_t": float(w.statistic), "p_welch": float(w.pvalue),
            "u": float(u.statistic), "p_u": float(u.pvalue),
            "u_method": "exact" if exact else "normal approximation (ties or large groups)",
            "d": float(d), "d_ci": [float(lo), float(hi)], "g": float(d * j),
            "d_note": note,
            "rank_biserial": float(1.0 - 2.0 * u.statistic / (n1 * n2)),
            "confidence": confidence}


def _fisher_ci(r, n, se_scale, confidence):
    if n <= 3 or abs(r) >= 1.0:
        return [float("nan"), float("nan")]
    z = math.atanh(r)
    h = stats.norm.ppf(0.5 + confidence / 2.0) * math.sqrt(se_scale / (n - 3))
    return [math.tanh(z - h), math.tanh(z + h)]


def correlate(x, y, *, confidence: float = CONFIDENCE) -> dict:
    """Spearman's rho and Pearson's R of a metric against scores (module docstring).

    Parameters
    ----------
    x, y : (n,) float
        Metric and (instructor) score per run, paired; n >= 3.

    Returns
    -------
    dict
        ``n``, ``rho``, ``p_rho``, ``rho_ci``, ``r``, ``p_r``, ``r_ci``.
    """
    x, y = _values(x, "x"), _values(y, "y")
    if len(x) != len(y) or len(x) < 3:
        raise ValueError(f"x and y must pair at least 3 values, got {len(x)} and {len(y)}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    n = len(x)
    s = stats.spearmanr(x, y)
    p = stats.pearsonr(x, y)
    return {"n": n, "rho": float(s.statistic), "p_rho": float(s.pvalue),
            "rho_ci": _fisher_ci(float(s.statistic), n, 1.06, confidence),
            "r": float(p.statistic), "p_r": float(p.pvalue),
            "r_ci": _fisher_ci(float(p.statistic), n, 1.0, confidence),
            "confidence": confidence}
