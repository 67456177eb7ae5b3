"""Group statistics a reviewer accepts: participants as the unit, a mixed
model over all runs, declared primary metrics and corrections.

The design (:func:`load_design`, ``metrics/design.toml`` by default) is
declared before the data: the unit of analysis, the primary metrics, the
corrections, and the metrics left out of the tests with the reason.

Per metric that is tested (:func:`group_statistics`):

Participants as the unit
    Each participant's mean over their runs (sessions); the group tests of
    :func:`metrics.validity.compare_groups` (t-test, Mann-Whitney U, Cohen's
    d with its interval, undefined with the reason when a group has no
    variance) run on those means, so repeated sessions never count as
    more people. ``unit = "run"`` in the design tests runs instead (the old,
    anti-conservative way; the report says so).
Mixed model
    ``value ~ group + session`` with a random intercept per participant
    (:class:`statsmodels.regression.mixed_linear_model.MixedLM`, REML; a fit
    the default optimizer leaves unconverged, as happens when the
    participant variance lies at its bound of 0, is refitted with Powell's
    method and says so) over every run: the novice-minus-expert group effect and the per-session
    effect with their standard errors and Wald p-values, and whether the fit
    converged. A metric with fewer than two participants per group, or one
    run per participant everywhere, is fitted without the session term.
Corrections
    The primary metrics form one family (``primary_correction``, Holm by
    default), every other tested metric another (``secondary_correction``,
    Benjamini-Hochberg by default); both Holm and BH are reported for each
    family (:func:`statsmodels.stats.multitest.multipletests`), and
    ``significant`` applies the family's declared correction to the
    per-participant t-test.
Classifier
    Each metric as a classifier of the groups on the participant means,
    oriented by its "better" direction (higher means expert for +1, lower
    for -1, the larger-AUC way for 0, which the table then says): AUC with
    Newcombe's interval (:func:`metrics.agreement.roc_auc`). Nothing is
    fitted, so no cross-validation is needed; the Naive Bayes score is
    already leave-one-participant-out.
Left out
    Declared exclusions (design constants, one quantity under two names),
    metrics constant over every run, and a metric whose values over the runs
    are an exact monotone copy of an earlier tested metric's (Spearman
    rho = 1 over every run with both; run values, not participant means, so
    that 16 means ranked alike by chance are not taken for a copy), each
    with its reason.
"""
from __future__ import annotations

import math
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["DESIGN_FILE", "Design", "load_design", "participant_means", "mixed_model",
           "screen_metrics", "correct", "group_statistics"]

#: Iterations of the Powell refit of a mixed model (see :func:`mixed_model`).
POWELL_MAXITER = 200

#: The default design, beside this module.
DESIGN_FILE = Path(__file__).with_name("design.toml")
_CORRECTIONS = {"holm": "holm", "fdr_bh": "fdr_bh", "bonferroni": "bonferroni"}


@dataclass(frozen=True)
class Design:
    """A study's declared statistical design (``design.toml`` documents each field).

    Attributes
    ----------
    unit : {"participant", "run"}
    alpha : float
    primary : tuple of str
    primary_correction, secondary_correction : str
        ``holm``, ``fdr_bh`` or ``bonferroni``.
    close_mm : float
        Distance [mm] within which force and tool speed are "close".
    excluded : dict of str -> str
        Metric -> reason it is not tested.
    source : str
        The file it was read from.
    """

    unit: str = "participant"
    alpha: float = 0.05
    primary: tuple = ()
    primary_correction: str = "holm"
    secondary_correction: str = "fdr_bh"
    close_mm: float = 8.0
    excluded: dict = field(default_factory=dict)
    source: str = ""

    def summary(self) -> dict:
        """JSON-ready."""
        return {"unit": self.unit, "alpha": self.alpha, "primary": list(self.primary),
                "primary_correction": self.primary_correction,
                "secondary_correction": self.secondary_correction,
                "close_mm": self.close_mm, "excluded": dict(self.excluded),
                "source": self.source}


def load_design(path=None) -> Design:
    """Read a design file (default :data:`DESIGN_FILE`).

    Raises
    ------
    BonesimError
        Naming the file and field: unreadable TOML, an unknown unit or
        correction, an alpha outside (0, 1), a non-positive ``close_mm``.
    """
    from bonesim.errors import BonesimError

    path = Path(DESIGN_FILE if path is None else path)
    try:
        d = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BonesimError(f"{path}: cannot read the design ({' '.join(str(exc).split())})") \
            from None
    unit = str(d.get("unit", "participant"))
    if unit not in ("participant", "run"):
        raise BonesimError(f"{path}: field 'unit': {unit!r} is not 'participant' or 'run'")
    alpha = d.get("alpha", 0.05)
    if not isinstance(alpha, (int, float)) or not 0.0 < alpha < 1.0:
        raise BonesimError(f"{path}: field 'alpha': {alpha!r} is not a number in (0, 1)")
    for k in ("primary_correction", "secondary_correction"):
        if str(d.get(k, "holm")) not in _CORRECTIONS:
            raise BonesimError(f"{path}: field {k!r}: {d[k]!r} is not one of "
                               f"{', '.join(_CORRECTIONS)}")
    close = d.get("close_mm", 8.0)
    if not isinstance(close, (int, float)) or not close > 0:
        raise BonesimError(f"{path}: field 'close_mm': {close!r} is not a positive number")
    prim = d.get("primary", [])
    if not isinstance(prim, list) or not all(isinstance(x, str) for x in prim):
        raise BonesimError(f"{path}: field 'primary': expected a list of metric names")
    exc = d.get("excluded", {})
    if not isinstance(exc, dict) or not all(isinstance(v, str) for v in exc.values()):
        raise BonesimError(f"{path}: table 'excluded': expected metric = \"reason\" lines")
    return Design(unit, float(alpha), tuple(prim), str(d.get("primary_correction", "holm")),
                  str(d.get("secondary_correction", "fdr_bh")), float(close), dict(exc),
                  str(path))


def participant_means(df, metric: str):
    """Each participant's mean of ``metric`` over their runs (finite values).

    Parameters
    ----------
    df : pandas.DataFrame
        The cohort table (``participant``, ``group``, ``metric``).

    Returns
    -------
    pandas.DataFrame
        ``participant, group, value, runs``; participants with a group only.
    """
    import pandas as pd

    d = df[df["group"].isin(["expert", "novice"]) & np.isfinite(df[metric].astype(float))]
    if not len(d):
        return pd.DataFrame(columns=["participant", "group", "value", "runs"])
    g = d.groupby("participant", sort=True)
    return pd.DataFrame({"participant": list(g.groups), "group": g["group"].first().to_numpy(),
                         "value": g[metric].mean().to_numpy(float),
                         "runs": g[metric].size().to_numpy(int)})


def mixed_model(df, metric: str) -> dict:
    """``metric ~ group + session`` with a random intercept per participant.

    Parameters
    ----------
    df : pandas.DataFrame
        The cohort table: ``participant``, ``group``, ``session`` (a number;
        NaN is taken as 1) and ``metric``; runs with a group only.

    Returns
    -------
    dict
        ``group_effect`` (novice minus expert, in the metric's unit),
        ``group_se``, ``p_group``, ``session_effect`` (per session),
        ``session_se``, ``p_session``, ``participant_sd`` and ``residual_sd``,
        ``runs``, ``participants``, ``converged``, ``formula`` and ``note``
        (empty, or why the fit was not made or is doubtful); NaN where not
        fitted.
    """
    import pandas as pd

    nan = math.nan
    out = {"group_effect": nan, "group_se": nan, "p_group": nan, "session_effect": nan,
           "session_se": nan, "p_session": nan, "participant_sd": nan, "residual_sd": nan,
           "runs": 0, "participants": 0, "converged": False, "formula": "", "note": ""}
    d = df[df["group"].isin(["expert", "novice"]) & np.isfinite(df[metric].astype(float))]
    d = pd.DataFrame({"y": d[metric].astype(float).to_numpy(),
                      "novice": (d["group"] == "novice").astype(float).to_numpy(),
                      "session": (d["session"].astype(float).fillna(1.0).to_numpy()
                                  if "session" in d else np.ones(len(d))),
                      "participant": d["participant"].astype(str).to_numpy()})
    out["runs"], out["participants"] = len(d), int(d["participant"].nunique())
    per = d.groupby("novice")["participant"].nunique()
    if len(per) < 2 or per.min() < 2:
        out["note"] = "fewer than two participants in a group"
        return out
    sd = float(d["y"].std(ddof=1))
    if not sd > 0:
        out["note"] = "constant over every run"
        return out
    with_session = d["session"].nunique() > 1
    formula = "y ~ novice + session" if with_session else "y ~ novice"
    out["formula"] = formula.replace("y", metric, 1)
    from statsmodels.regression.mixed_linear_model import MixedLM

    # fit on the standardized metric (stable optimizer), report in its unit
    mu = float(d["y"].mean())
    z = d.assign(y=(d["y"] - mu) / sd)
    model = MixedLM.from_formula(formula, z, groups=z["participant"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fit = model.fit(reml=True)
        except (np.linalg.LinAlgError, ValueError) as exc:
            out["note"] = f"not fitted ({' '.join(str(exc).split())})"
            return out
    refit = ""
    if not getattr(fit, "converged", False):
        # a participant variance at its bound of 0 stalls the gradient
        # methods; Powell's derivative-free search converges there, in 2 or 3
        # iterations where it does (the variance is one parameter); where it
        # does not, more iterations did not help (5,000 took 80 s per metric
        # and still failed), so it stops at POWELL_MAXITER
        with warnings.catch_warnings(record=True) as again:
            warnings.simplefilter("always")
            try:
                alt = model.fit(reml=True, method="powell", maxiter=POWELL_MAXITER)
            except (np.linalg.LinAlgError, ValueError):
                alt = None
        if alt is not None and getattr(alt, "converged", False):
            fit, caught, refit = alt, again, "refitted with Powell's method (converged)"
    out["converged"] = bool(getattr(fit, "converged", False))
    notes = sorted({str(w.message).split("\n")[0] for w in caught
                    if "converge" in str(w.message).lower()
                    or "boundary" in str(w.message).lower()})
    if refit:
        notes.append(refit)
    if notes:
        out["note"] = "; ".join(notes)
    fe, se, p = fit.fe_params, fit.bse_fe, fit.pvalues
    out.update(group_effect=float(fe["novice"]) * sd, group_se=float(se["novice"]) * sd,
               p_group=float(p["novice"]))
    if with_session:
        out.update(session_effect=float(fe["session"]) * sd,
                   session_se=float(se["session"]) * sd, p_session=float(p["session"]))
    cov = np.asarray(fit.cov_re, float).reshape(-1)
    out["participant_sd"] = float(math.sqrt(max(cov[0], 0.0))) * sd if len(cov) else nan
    out["residual_sd"] = float(math.sqrt(fit.scale)) * sd
    return out


def screen_metrics(df, metrics, design: Design) -> dict:
    """Metrics that are not tested, with the reason (module docstring).

    Parameters
    ----------
    df : pandas.DataFrame
        The cohort table.
    metrics : sequence of str
        Candidate metric columns, in table order (an earlier metric keeps
        its place when a later one copies it).
    design : Design

    Returns
    -------
    dict
        Metric -> reason, for every metric left out.
    """
    from scipy import stats

    out = {}
    kept = {}
    for m in metrics:
        if m in design.excluded:
            out[m] = design.excluded[m]
            continue
        v = df[m].astype(float).to_numpy()
        v = v[np.isfinite(v)]
        if not len(v):
            out[m] = "no values"
            continue
        if np.ptp(v) == 0:
            out[m] = f"constant ({v[0]:.6g}) over every run"
            continue
        key = df.loc[np.isfinite(df[m].astype(float)), m].astype(float)
        for other, ov in kept.items():
            both = key.index.intersection(ov.index)
            if len(both) >= 3 and np.ptp(key[both]) > 0 and np.ptp(ov[both]) > 0:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    rho = stats.spearmanr(key[both], ov[both]).statistic
                if abs(rho) > 1.0 - 1e-12:
                    out[m] = f"a monotone copy of {other} (Spearman rho {rho:+.0f})"
                    break
        else:
            kept[m] = key
    return out


def correct(p, method: str) -> np.ndarray:
    """``p``-values adjusted by ``method`` (``holm``, ``fdr_bh``, ``bonferroni``);
    NaN stays NaN and is not counted in the family.

    Holm's step-down adjustment is computed here (:func:`_holm`, the values
    of :func:`statsmodels.stats.multitest.multipletests`, which the tests
    check): statsmodels runs a full garbage collection on each Holm call,
    a quarter of a second in a process holding a cohort. The others are
    statsmodels'."""
    from statsmodels.stats.multitest import multipletests

    p = np.asarray(p, float)
    out = np.full(len(p), np.nan)
    ok = np.isfinite(p)
    if ok.any():
        out[ok] = _holm(p[ok]) if method == "holm" else \
            multipletests(p[ok], method=_CORRECTIONS[method])[1]
    return out


def _holm(p: np.ndarray) -> np.ndarray:
    """Holm's adjusted p-values of a family of ``m`` p-values: in ascending
    order the ``i``-th (from 0) is ``min(1, max over j <= i of (m - j) p_(j))``."""
    m = len(p)
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    out = np.empty(m)
    out[order] = adj
    return out


def _auc(pm, better: int) -> dict:
    from metrics.agreement import roc_auc

    e = (pm["group"] == "expert").to_numpy()
    v = pm["value"].to_numpy(float)
    if e.sum() < 1 or (~e).sum() < 1:
        return {}
    if better == 0:
        up, down = roc_auc(v, e), roc_auc(-v, e)
        r, orient = (up, "higher") if up["auc"] >= down["auc"] else (down, "lower")
        orient += " (chosen after the fact)"
    else:
        r, orient = roc_auc(v if better > 0 else -v, e), "higher" if better > 0 else "lower"
    return {"auc": r["auc"], "auc_lo": r["auc_ci"][0], "auc_hi": r["auc_ci"][1],
            "auc_expert_is": orient}


def group_statistics(df, columns: dict, design: Design | None = None):
    """The statistics table of a cohort (module docstring).

    Parameters
    ----------
    df : pandas.DataFrame
        The cohort table: ``participant``, ``group``, ``instructor_score``,
        ``session`` and the metric columns.
    columns : dict
        Metric -> ``(unit, better)`` (:data:`metrics.cohort_result.METRIC_COLUMNS`
        and any extra columns).
    design : Design, optional
        Default :func:`load_design`.

    Returns
    -------
    (pandas.DataFrame, dict)
        One row per tested metric (columns listed in
        :data:`metrics.cohort_result.STATS_COLUMNS`), and the metrics left
        out with their reasons.
    """
    import pandas as pd

    from metrics.cohort_result import STATS_COLUMNS
    from metrics.validity import compare_groups, correlate

    design = load_design() if design is None else design
    excluded = screen_metrics(df, list(columns), design)
    rows = []
    for name, (unit, better) in columns.items():
        if name in excluded:
            continue
        pm = participant_means(df, name)
        if design.unit == "participant":
            a = pm.loc[pm["group"] == "expert", "value"].to_numpy(float)
            b = pm.loc[pm["group"] == "novice", "value"].to_numpy(float)
        else:
            v = df[name].astype(float)
            a = v[(df["group"] == "expert") & np.isfinite(v)].to_numpy(float)
            b = v[(df["group"] == "novice") & np.isfinite(v)].to_numpy(float)
        if len(a) < 2 or len(b) < 2:
            excluded[name] = f"fewer than 2 {design.unit}s with a value in a group " \
                f"({len(a)} expert, {len(b)} novice)"
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = compare_groups(a, b)
        row = {"metric": name, "unit": unit, "better": better,
               "family": "primary" if name in design.primary else "secondary"}
        for grp in ("expert", "novice"):
            for k in ("n", "mean", "sd"):
                row[f"{grp}_{k}"] = r[grp][k]
        row.update(t=r["t"], p_t=r["p_t"], u=r["u"], p_u=r["p_u"], u_method=r["u_method"],
                   d=r["d"], d_lo=r["d_ci"][0], d_hi=r["d_ci"][1], d_note=r["d_note"])
        row.update(_auc(pm, better))
        mm = mixed_model(df, name)
        row.update({f"mixed_{k}": mm[k] for k in ("group_effect", "group_se", "p_group",
                                                  "session_effect", "session_se",
                                                  "p_session", "converged", "note")})
        sc = df[["participant", "instructor_score"]].groupby("participant").mean()
        both = pm.set_index("participant").join(sc, how="inner").dropna()
        c = None
        if len(both) >= 3 and np.ptp(both["value"]) > 0 and np.ptp(both["instructor_score"]) > 0:
            c = correlate(both["value"], both["instructor_score"])
        for k in ("rho", "p_rho", "r", "p_r"):
            row[k] = c[k] if c else math.nan
        rows.append(row)
    st = pd.DataFrame(rows)
    if not len(st):
        return pd.DataFrame(columns=list(STATS_COLUMNS)), excluded
    for fam in ("primary", "secondary"):
        sel = (st["family"] == fam).to_numpy()
        declared = design.primary_correction if fam == "primary" else \
            design.secondary_correction
        for col in ("p_t", "mixed_p_group"):
            base = col if col == "p_t" else "p_mixed"
            st.loc[sel, f"{base}_holm"] = correct(st.loc[sel, col], "holm")
            st.loc[sel, f"{base}_bh"] = correct(st.loc[sel, col], "fdr_bh")
            st.loc[sel, f"{base}_adj"] = correct(st.loc[sel, col], declared)
        st.loc[sel, "correction"] = declared
    st["significant"] = st["p_t_adj"] < design.alpha
    st["mixed_significant"] = st["p_mixed_adj"] < design.alpha
    for c in STATS_COLUMNS:
        if c not in st:
            st[c] = math.nan
    return st[list(STATS_COLUMNS)].reset_index(drop=True), excluded
