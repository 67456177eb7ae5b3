"""Learning curves: each participant's metric session by session against
the experts' band (``bonesim metrics progress``).

:func:`learning_curves` reads a scored cohort's table (a row per run with
``participant``, ``group``, ``session``); :func:`draw_progress` draws one
panel per metric: every participant's runs joined in session order (thin,
coloured by group), each group's mean per session (thick), and the experts'
band, the mean +- 1 SD of the expert runs of every session (shaded), the
level a trainee is to reach. :func:`improvement` gives each participant's
least-squares slope per session, oriented so that positive is better
(``better`` of :data:`metrics.cohort_result.METRIC_COLUMNS`), and its mean
per group.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["DEFAULT_METRICS", "improvement", "draw_progress"]

#: Panels drawn by default (those the table has).
DEFAULT_METRICS = ("visible_fraction", "nb_score_per_voxel", "force_close_n",
                   "tool_speed_close_mm_s", "mean_plunge", "exceedances_close",
                   "assess_share")    # the final product's share of the scale's points
_COLOURS = {"expert": "#1f77b4", "novice": "#d62728"}


def _runs(df, metric):
    d = df[df["group"].isin(["expert", "novice"])]
    d = d[np.isfinite(d[metric].astype(float)) & np.isfinite(d["session"].astype(float))]
    return d.sort_values(["participant", "session"])


def improvement(df, metric: str, better: int) -> dict:
    """Per participant the slope of ``metric`` over sessions, times ``better``
    (0 counts as +1), and the mean slope per group.

    Returns
    -------
    dict
        ``participants``: ``id -> slope`` [metric unit per session, oriented];
        ``expert`` and ``novice``: mean slope (NaN without a participant of
        two sessions or more); ``improving``: share of novices with a
        positive oriented slope.
    """
    d = _runs(df, metric)
    sign = -1.0 if better < 0 else 1.0
    per, group = {}, {}
    for pid, x in d.groupby("participant"):
        if x["session"].nunique() >= 2:
            per[pid] = sign * float(np.polyfit(x["session"].astype(float),
                                               x[metric].astype(float), 1)[0])
            group[pid] = x["group"].iloc[0]
    out = {"participants": per}
    for g in ("expert", "novice"):
        v = [s for p, s in per.items() if group[p] == g]
        out[g] = float(np.mean(v)) if v else math.nan
    nov = [s for p, s in per.items() if group[p] == "novice"]
    out["improving"] = float(np.mean([s > 0 for s in nov])) if nov else math.nan
    return out


def draw_progress(df, path, metrics=None, columns=None, title: str = "") -> dict:
    """Draw the learning curves (module docstring) to a PNG.

    Parameters
    ----------
    df : pandas.DataFrame
        The cohort table.
    path : path
        The PNG to write.
    metrics : sequence of str, optional
        Panels (default :data:`DEFAULT_METRICS` that have values).
    columns : dict, optional
        Metric -> ``(unit, better)`` (default
        :data:`metrics.cohort_result.METRIC_COLUMNS`).
    title : str

    Returns
    -------
    dict
        ``png`` and per metric :func:`improvement`.

    Raises
    ------
    ValueError
        If no metric has values over sessions.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from metrics.cohort_result import METRIC_COLUMNS

    columns = dict(METRIC_COLUMNS if columns is None else columns)
    want = list(DEFAULT_METRICS if metrics is None else metrics)
    have = [m for m in want if m in df and len(_runs(df, m))]
    if not have:
        raise ValueError(f"no values over sessions for {', '.join(want)}")
    ncol = min(3, len(have))
    nrow = int(math.ceil(len(have) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.6 * nrow), squeeze=False)
    out = {"png": str(path), "metrics": {}}
    for ax, m in zip(axes.ravel(), have):
        d = _runs(df, m)
        unit, better = columns.get(m, ("", 0))
        sessions = np.sort(d["session"].unique())
        e = d[d["group"] == "expert"]
        if len(e):
            mu, sd = float(e[m].mean()), float(e[m].std(ddof=1)) if len(e) > 1 else 0.0
            ax.axhspan(mu - sd, mu + sd, color=_COLOURS["expert"], alpha=0.15,
                       label="experts: mean +- 1 SD")
        for pid, x in d.groupby("participant"):
            ax.plot(x["session"], x[m], "-o", ms=2.5, lw=0.8, alpha=0.45,
                    color=_COLOURS[x["group"].iloc[0]])
        for g in ("expert", "novice"):
            x = d[d["group"] == g].groupby("session")[m].mean()
            if len(x):
                ax.plot(x.index, x.to_numpy(), "-", lw=2.6, color=_COLOURS[g],
                        label=f"{g}s: mean")
        imp = improvement(df, m, better)
        out["metrics"][m] = imp
        arrow = {1: " (higher is better)", -1: " (lower is better)"}.get(better, "")
        ax.set_title(f"{m}{arrow}\nnovice slope {imp['novice']:+.3g}/session "
                     f"(oriented; {imp['improving'] * 100:.0f} % improve)", fontsize=8.5)
        ax.set_xlabel("session")
        ax.set_ylabel(f"{m} [{unit}]" if unit else m, fontsize=8)
        ax.set_xticks(sessions)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(have):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7, loc="best")
    fig.suptitle(title or "Learning curves: each participant by session, against the "
                 "experts' band", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return out
