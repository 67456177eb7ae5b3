"""Agreement and classification: ICC, Bland-Altman, ROC and AUC.

What a reviewer of a validation study asks beside the group tests
(``SPEC.md``, "Construct validity"): do two measurements of the same
participants agree (test-retest between sessions, a metric against an
instructor's score), and how well does a metric tell the groups apart?

Intraclass correlation (:func:`icc`)
    Shrout & Fleiss (1979) from the two-way ANOVA of an ``(n targets, k
    raters)`` table: mean squares of rows ``MSR``, columns ``MSC`` and error
    ``MSE``. ``ICC(2,1)`` (two-way random effects, absolute agreement, single
    measurement; McGraw & Wong's ICC(A,1)) is
    ``(MSR - MSE) / (MSR + (k - 1) MSE + k (MSC - MSE) / n)``; its confidence
    interval is Shrout & Fleiss' approximate F interval (Satterthwaite degrees
    of freedom ``v``). ``ICC(1,1)`` and ``ICC(3,1)`` come with it.
Bland-Altman (:func:`bland_altman`)
    Bias (mean of the differences ``a - b``), the limits of agreement
    ``bias +- z sd`` (``z`` the normal quantile of the level, 1.96 for 95 %),
    and the confidence intervals of the bias (t) and of each limit (the
    standard error ``sd sqrt(1/n + z^2 / (2 (n - 1)))`` of Bland & Altman 1999).
ROC and AUC (:func:`roc_auc`)
    The empirical ROC curve of a score (higher: positive class) and its area,
    ``AUC = P(score of a positive > score of a negative) + P(tie) / 2`` (the
    Mann-Whitney U over ``n1 n2``), with DeLong's (1988) standard error and
    Newcombe's (2006, method 5) score interval: the AUCs ``A`` with
    ``|AUC - A| = z sqrt(V(A))``, ``V(A) = A (1 - A) / (m n) [2N - 1 -
    (3N - 3) / ((2 - A)(1 + A))]``, ``N = (m + n) / 2``. Like Wilson's interval
    for a proportion it stays inside [0, 1] and is not degenerate at perfect
    separation (where a Wald interval on DeLong's variance is the point).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import stats

__all__ = ["CONFIDENCE", "icc", "bland_altman", "roc_auc"]

#: Confidence level of every interval.
CONFIDENCE = 0.95


def icc(table, *, confidence: float = CONFIDENCE) -> dict:
    """Intraclass correlations of an ``(n, k)`` table (module docstring).

    Parameters
    ----------
    table : (n, k) float
        ``n`` targets (participants) rated by ``k`` raters (sessions,
        instructor and metric, ...); finite, ``n >= 2``, ``k >= 2``.
    confidence : float
        Interval level, in (0, 1).

    Returns
    -------
    dict
        ``icc2_1`` with ``icc2_1_ci`` (two-way random, absolute agreement,
        single measurement), ``icc1_1``, ``icc3_1``, the mean squares
        ``msr, msc, mse``, ``f`` (``MSR / MSE``) with ``p`` and ``df``,
        ``n``, ``k``.

    Raises
    ------
    ValueError
        On a table that is not 2-D with at least 2 x 2 finite values, or a
        bad ``confidence``.
    """
    x = np.asarray(table, np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or x.shape[1] < 2:
        raise ValueError(f"table must be (n targets, k raters) with n, k >= 2, got shape "
                         f"{x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("table: values must be finite (drop targets with a missing rating)")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    n, k = x.shape
    grand = x.mean()
    ss_r = k * np.sum((x.mean(axis=1) - grand) ** 2)
    ss_c = n * np.sum((x.mean(axis=0) - grand) ** 2)
    ss_t = np.sum((x - grand) ** 2)
    ss_e = ss_t - ss_r - ss_c
    msr, msc = ss_r / (n - 1), ss_c / (k - 1)
    mse = ss_e / ((n - 1) * (k - 1))
    msw = (ss_c + ss_e) / (n * (k - 1))
    icc1 = (msr - msw) / (msr + (k - 1) * msw)
    icc3 = (msr - mse) / (msr + (k - 1) * mse)
    icc2 = (msr - mse) / (msr + (k - 1) * mse + k * (msc - mse) / n)
    # Shrout & Fleiss' interval for ICC(2,1)
    a = 1.0 - confidence
    fj = msc / mse if mse > 0 else math.inf
    vn = (k - 1) * (n - 1) * (k * icc2 * fj + n * (1 + (k - 1) * icc2) - k * icc2) ** 2
    vd = (n - 1) * k ** 2 * icc2 ** 2 * fj ** 2 + (n * (1 + (k - 1) * icc2) - k * icc2) ** 2
    if math.isfinite(fj) and vd > 0:
        v = vn / vd
        fu = stats.f.ppf(1 - a / 2, n - 1, v)
        fl = stats.f.ppf(1 - a / 2, v, n - 1)
        lo = n * (msr - fu * mse) / (fu * (k * msc + (k * n - k - n) * mse) + n * msr)
        hi = n * (fl * msr - mse) / (k * msc + (k * n - k - n) * mse + n * fl * msr)
    else:
        lo = hi = math.nan
    f = msr / mse if mse > 0 else math.inf
    df1, df2 = n - 1, (n - 1) * (k - 1)
    return {"n": n, "k": k, "icc2_1": float(icc2), "icc2_1_ci": [float(lo), float(hi)],
            "icc1_1": float(icc1), "icc3_1": float(icc3), "msr": float(msr),
            "msc": float(msc), "mse": float(mse), "f": float(f), "df": [df1, df2],
            "p": float(stats.f.sf(f, df1, df2)) if math.isfinite(f) else 0.0,
            "confidence": confidence,
            "kind": "ICC(2,1): two-way random effects, absolute agreement, single measure"}


def bland_altman(a, b, *, confidence: float = CONFIDENCE) -> dict:
    """Bland-Altman agreement of paired measurements ``a`` and ``b``.

    Parameters
    ----------
    a, b : (n,) float
        The two methods' (or sessions') values, paired; finite, ``n >= 3``.
    confidence : float
        Level of the limits and of the intervals, in (0, 1).

    Returns
    -------
    dict
        ``n``, ``bias`` (mean of ``a - b``), ``sd`` (sample sd of the
        differences), ``loa`` ``[lower, upper]``, ``bias_ci``, ``lower_ci``,
        ``upper_ci``, and per pair ``mean`` and ``diff`` (the plot's axes).
    """
    a = np.asarray(a, np.float64).reshape(-1)
    b = np.asarray(b, np.float64).reshape(-1)
    if len(a) != len(b) or len(a) < 3:
        raise ValueError(f"a and b must pair at least 3 values, got {len(a)} and {len(b)}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("a, b: values must be finite")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    d = a - b
    n = len(d)
    bias, sd = float(d.mean()), float(d.std(ddof=1))
    z = float(stats.norm.ppf(0.5 + confidence / 2))
    tq = float(stats.t.ppf(0.5 + confidence / 2, n - 1))
    se_b = sd / math.sqrt(n)
    se_l = sd * math.sqrt(1.0 / n + z * z / (2.0 * (n - 1)))
    lo, hi = bias - z * sd, bias + z * sd
    return {"n": n, "bias": bias, "sd": sd, "loa": [lo, hi],
            "bias_ci": [bias - tq * se_b, bias + tq * se_b],
            "lower_ci": [lo - tq * se_l, lo + tq * se_l],
            "upper_ci": [hi - tq * se_l, hi + tq * se_l],
            "mean": ((a + b) / 2).tolist(), "diff": d.tolist(), "confidence": confidence}


def roc_auc(score, positive, *, confidence: float = CONFIDENCE) -> dict:
    """ROC curve and AUC of ``score`` for ``positive`` (module docstring).

    Parameters
    ----------
    score : (n,) float
        Higher means "more likely positive" (orient a lower-is-better metric
        by negating it first).
    positive : (n,) bool
        The true class; both classes present.
    confidence : float

    Returns
    -------
    dict
        ``auc``, ``auc_ci`` (Newcombe), ``se`` (DeLong), ``n_pos``,
        ``n_neg``, ``fpr``, ``tpr`` (the curve, from (0, 0) to (1, 1)),
        ``thresholds``, and ``note`` ("perfect separation" or "").
    """
    s = np.asarray(score, np.float64).reshape(-1)
    y = np.asarray(positive, bool).reshape(-1)
    if len(s) != len(y):
        raise ValueError(f"score has {len(s)} values, positive {len(y)}")
    if not np.isfinite(s).all():
        raise ValueError("score: values must be finite")
    x, z = s[y], s[~y]
    m, n = len(x), len(z)
    if m < 1 or n < 1:
        raise ValueError(f"both classes need a value, got {m} positive and {n} negative")
    psi = (x[:, None] > z[None, :]) + 0.5 * (x[:, None] == z[None, :])
    auc = float(psi.mean())
    v10, v01 = psi.mean(axis=1), psi.mean(axis=0)
    var = (v10.var(ddof=1) / m if m > 1 else 0.0) + (v01.var(ddof=1) / n if n > 1 else 0.0)
    se = math.sqrt(max(var, 0.0))
    lo, hi = _newcombe(auc, m, n, float(stats.norm.ppf(0.5 + confidence / 2)))
    note = "perfect separation" if auc in (0.0, 1.0) else ""
    thr = np.unique(s)[::-1]
    tpr = [0.0] + [float(np.mean(x >= t)) for t in thr]
    fpr = [0.0] + [float(np.mean(z >= t)) for t in thr]
    return {"auc": auc, "auc_ci": [lo, hi], "se": se, "ci_method": "Newcombe 2006 (5)",
            "n_pos": m, "n_neg": n, "fpr": fpr, "tpr": tpr, "thresholds": thr.tolist(),
            "note": note, "confidence": confidence}


def _newcombe(auc: float, m: int, n: int, z: float) -> tuple[float, float]:
    """Newcombe's score interval of an AUC of ``m`` positives, ``n`` negatives."""
    from scipy.optimize import brentq

    big = 0.5 * (m + n)

    def gap(a):                      # > 0 outside the interval
        v = a * (1 - a) / (m * n) * (2 * big - 1 - (3 * big - 3) / ((2 - a) * (1 + a)))
        return (auc - a) ** 2 - z * z * max(v, 0.0)

    eps = 1e-9                       # V(a) is 0 at a = 0 and 1: bracket just inside
    inner_lo, inner_hi = min(max(auc, eps), 1 - eps), max(min(auc, 1 - eps), eps)
    lo = 0.0 if gap(0.0) <= 0 else brentq(gap, 0.0, inner_lo)
    hi = 1.0 if gap(1.0) <= 0 else brentq(gap, inner_hi, 1.0)
    return float(lo), float(hi)
