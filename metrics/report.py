"""A scored cohort as one self-contained HTML page for a researcher.

:func:`write_report` draws a :class:`metrics.cohort_result.CohortResult` (what
:mod:`metrics.cohort` fills) into a single HTML file: the plots are PNGs
embedded as ``data:`` URLs, the style is inline, and nothing is fetched from
anywhere (no scripts, fonts or links), so the page can be mailed or archived
as is. Sections, after the figures a construct-validity paper shows (the
thesis' figures 18 to 21 and ``SPEC.md``, "Metrics"):

0. Design and provenance (:func:`metrics.report_design.design_section`):
   participants and sessions per group, unit of analysis, primary metrics
   and corrections, metrics left out with the reason, bonesim version, case
   and burr hashes, participants-file hash, synthesis seed, command line.
1. Cohort: runs and participants per group, case, how and when it was
   scored (``meta``), a notice when the runs are synthetic test data, and
   every error (failed runs, participants without runs).
2. Scores by group: per metric, each run's value (jittered sideways) over
   its group's mean and 95 % t confidence interval; the two-tailed t-test
   and Mann-Whitney U p-values in the title.
3. Instructor score against visible fraction and Naive Bayes score (score on
   the x axis, as in the thesis): points coloured by group, least-squares
   line, Pearson's R and its p in the title.
4. Force against distance to the structure: per group and 2 mm bin, the
   mean force with its 95 % confidence interval
   (:func:`metrics.forces.group_bins`).
5. Visibility views of chosen runs (:func:`metrics.visibility.render_visibility`,
   offscreen OpenGL); skipped with a note where rendering is unavailable.
6. Every metric's statistics with units and better direction (corrected
   p < alpha highlighted; :func:`metrics.report_design.stats_section`), the
   Naive Bayes ROC and the test-retest agreement (ICC, Bland-Altman), the
   per-run table and the Naive Bayes training sets (both collapsible).

Reading the result: the per-group columns of ``stats`` are taken as
``<group>_<n|mean|sd>`` (``expert_mean``; ``mean_expert`` is accepted too);
the runs are synthetic when ``meta["synthetic"]`` is true or a ``notes``
column of ``table`` (the session headers' notes) or ``meta["notes"]`` says
"synthetic"; a file's group is its ``table`` row's, else its force table's.

Every string from the data is escaped (:func:`html.escape`); a missing or
undefined number (NaN) reads "n/a". Plots use matplotlib's Agg backend.
"""
from __future__ import annotations

import base64
import html
import io
import math
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from bonesim.io.anatomy import clinical_name

__all__ = ["FIG_SIZE", "SMALL_FIG_SIZE", "DPI", "GROUP_COLOURS", "OTHER_COLOUR", "GROUP_ORDER",
           "KEY_METRICS", "SCATTER_METRICS", "ALPHA", "CONFIDENCE", "JITTER", "NA",
           "write_report"]

#: Size of the large figures (force profile, scatter plots) [inches].
FIG_SIZE = (6.4, 4.2)
#: Size of the per-metric group plots [inches].
SMALL_FIG_SIZE = (4.2, 3.4)
#: Resolution of the embedded PNGs [dots per inch].
DPI = 100
#: Colour of each group in every plot.
GROUP_COLOURS = {"expert": "#1f77b4", "novice": "#d62728"}
#: Colour of runs of any other (or no) group.
OTHER_COLOUR = "#7f7f7f"
#: Groups in the order they are drawn and tabulated (others follow, sorted).
GROUP_ORDER = ("expert", "novice")
#: Metrics drawn first and large in the group section.
KEY_METRICS = ("visible_fraction", "nb_score", "force_near_n")
#: Metrics plotted against the instructor score.
SCATTER_METRICS = ("visible_fraction", "nb_score")
#: p-values below this are highlighted.
ALPHA = 0.05
#: Level of the plotted confidence intervals.
CONFIDENCE = 0.95
#: Half-width of the sideways jitter of the per-run points [group spacing].
JITTER = 0.12
#: What a missing or undefined number reads.
NA = "n/a"

_CSS = """
body{font-family:sans-serif;max-width:1180px;margin:1.5em auto;padding:0 1em;color:#222;
line-height:1.4}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0}
th,td{border:1px solid #ccc;padding:.2em .45em;text-align:right;vertical-align:top}
th{background:#f0f0f0}td.l,th.l{text-align:left}
td.sig{background:#fff2a8;font-weight:bold}tr.err td{background:#fde4e4}
.notice{background:#fff3cd;border:2px solid #d9a400;padding:.6em 1em;font-weight:bold}
.errors{background:#fde4e4;border:1px solid #d66;padding:.4em 1em}
.grid{display:flex;flex-wrap:wrap;gap:.6em}.grid figure{margin:0}
figcaption{font-size:.8em;color:#555;max-width:480px}
.note{color:#555;font-style:italic}dl{display:grid;grid-template-columns:max-content auto;
gap:.1em 1em}dt{font-weight:bold}dd{margin:0}
details{margin:.6em 0}summary{cursor:pointer;font-weight:bold}
"""


# ------------------------------------------------------------------ formatting
def _esc(x) -> str:
    """Any value as escaped HTML text."""
    return html.escape(str(x), quote=True)


def _isnan(x) -> bool:
    if x is None:
        return True
    try:
        return math.isnan(float(x))
    except (TypeError, ValueError):
        return False


def _num(x, digits: int = 3) -> str:
    """A number with ``digits`` significant digits; NaN and None read :data:`NA`."""
    if _isnan(x):
        return NA
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return str(int(x))
    v = float(x)
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if v == int(v) and abs(v) < 1e6:
        return str(int(v))
    return f"{v:.{digits}g}"


def _p(x) -> str:
    """A p-value: ``< 0.001`` below it, else three decimals."""
    if _isnan(x):
        return NA
    return "< 0.001" if float(x) < 0.001 else f"{float(x):.3f}"


def _p_is(x) -> str:
    """``"p = 0.012"`` or ``"p < 0.001"`` (for titles)."""
    v = _p(x)
    return f"p {v}" if v.startswith("<") else f"p = {v}"


def _sig(x) -> bool:
    return not _isnan(x) and float(x) < ALPHA


def _cell(text: str, *, left: bool = False, sig: bool = False) -> str:
    cls = " ".join(c for c, on in (("l", left), ("sig", sig)) if on)
    return f"<td class=\"{cls}\">{text}</td>" if cls else f"<td>{text}</td>"


def _name(path) -> str:
    return Path(str(path)).name


# ------------------------------------------------------------------ data access
def _groups(table) -> list:
    """Groups present, :data:`GROUP_ORDER` first."""
    present = [str(g) for g in table["group"].fillna("").unique()]
    return [g for g in GROUP_ORDER if g in present] + \
        sorted(g for g in present if g not in GROUP_ORDER)


def _colour(group: str) -> str:
    return GROUP_COLOURS.get(group, OTHER_COLOUR)


def _label(group: str) -> str:
    return group or "(no group)"


def _stats_row(result, metric):
    """The ``stats`` row of ``metric`` as a dict, or ``{}``."""
    st = result.stats
    if st is None or len(st) == 0 or "metric" not in st:
        return {}
    rows = st[st["metric"] == metric]
    return rows.iloc[0].to_dict() if len(rows) else {}


def _group_stat(row: dict, group: str, key: str):
    """``<group>_<key>`` (or ``<key>_<group>``) of a stats row; NaN if absent."""
    for k in (f"{group}_{key}", f"{key}_{group}"):
        if k in row:
            return row[k]
    return math.nan


def _values(table, metric, group) -> np.ndarray:
    v = table.loc[table["group"].fillna("") == group, metric].to_numpy(dtype=float)
    return v[np.isfinite(v)]


def _mean_ci(v: np.ndarray):
    """Mean and t confidence interval of ``v`` (NaN bounds under two values)."""
    from scipy import stats

    if len(v) == 0:
        return math.nan, math.nan, math.nan
    m = float(v.mean())
    if len(v) < 2:
        return m, math.nan, math.nan
    h = stats.t.ppf(0.5 + CONFIDENCE / 2, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v))
    return m, m - h, m + h


def _synthetic(result) -> bool:
    """Whether the runs say they are synthetic test data."""
    meta = result.meta or {}
    if meta.get("synthetic"):
        return True
    texts = [str(meta.get("notes", ""))]
    if "notes" in getattr(result.table, "columns", ()):
        texts += [str(x) for x in result.table["notes"].fillna("")]
    return any("synthetic" in t.lower() for t in texts)


# ------------------------------------------------------------------ figures
class _Figures:
    """Turns matplotlib figures into embedded ``<img>`` tags (and PNG files)."""

    def __init__(self, png_dir):
        self.png_dir = None if png_dir is None else Path(png_dir)
        if self.png_dir is not None:
            self.png_dir.mkdir(parents=True, exist_ok=True)
        self.written = []

    def png(self, data: bytes, stem: str, alt: str) -> str:
        if self.png_dir is not None:
            p = self.png_dir / f"{stem}.png"
            p.write_bytes(data)
            self.written.append(p)
        b64 = base64.b64encode(data).decode("ascii")
        return f"<img src=\"data:image/png;base64,{b64}\" alt=\"{_esc(alt)}\">"

    def fig(self, fig, stem: str, alt: str) -> str:
        import matplotlib.pyplot as plt

        buf = io.BytesIO()
        fig.tight_layout()
        fig.savefig(buf, format="png", dpi=DPI)
        plt.close(fig)
        return self.png(buf.getvalue(), stem, alt)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _axis_label(metric: str) -> str:
    from metrics.cohort_result import METRIC_COLUMNS

    unit = METRIC_COLUMNS.get(metric, ("", 0))[0]
    return f"{metric} [{unit}]" if unit else metric


def _people(table, metric, group):
    """``(participant means, their runs)`` of ``group``: each participant's
    mean of ``metric`` over their runs (the unit of the statistics,
    :func:`metrics.group_stats.participant_means`) and the runs' own values
    with the index of their participant in the means, ``(p,)``, ``(r,)``, ``(r,)``."""
    from metrics.group_stats import participant_means

    pm = participant_means(table, metric)
    pm = pm[pm["group"] == group].reset_index(drop=True)
    t = table[(table["group"].fillna("") == group) &
              np.isfinite(table[metric].astype(float))]
    where = {p: q for q, p in enumerate(pm["participant"])}
    idx = np.array([where[p] for p in t["participant"]], np.int64)
    return pm["value"].to_numpy(float), t[metric].to_numpy(float), idx


def _group_plot(result, metric, groups, big: bool):
    """One point per participant (the mean over their sessions, the unit the
    tests use) over the group mean +- CI of those means; each session a faint
    small dot on its participant's vertical."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=FIG_SIZE if big else SMALL_FIG_SIZE)
    rng = np.random.default_rng(0)
    counts = []
    for q, g in enumerate(groups):
        people, runs, who = _people(result.table, metric, g)
        counts.append((len(people), len(runs)))
        c = _colour(g)
        if len(people):
            x = q + rng.uniform(-JITTER, JITTER, len(people))
            ax.scatter(x[who], runs, s=7, color=c, alpha=0.25, zorder=2, edgecolor="none",
                       label="a session" if q == 0 else None)
            ax.scatter(x, people, s=30, color=c, alpha=0.9, zorder=3, edgecolor="white",
                       linewidth=0.5, label="a participant (mean)" if q == 0 else None)
        else:
            ax.text(q, 0.5, "no values", ha="center", va="center", color=c,
                    transform=ax.get_xaxis_transform())
        m, lo, hi = _mean_ci(people)
        if not _isnan(m):
            err = None if _isnan(lo) else [[m - lo], [hi - m]]
            ax.errorbar(q + 0.3, m, yerr=err, fmt="s", color=c, capsize=6, ms=7,
                        zorder=4, lw=1.8)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels([f"{_label(g)}\n({n} people, {r} runs)"
                        for g, (n, r) in zip(groups, counts)])
    ax.set_xlim(-0.5, len(groups) - 0.3)
    ax.set_ylabel(_axis_label(metric))
    row = _stats_row(result, metric)
    p_t, p_mixed = row.get("p_t_adj"), row.get("p_mixed_adj")
    corr = f" {row.get('correction')}" if not _isnan(p_t) else ""
    sep = ", " if big else "\n"                  # small panels: one test a line
    ax.set_title(f"{metric}\nper participant t-test{corr} {_p_is(p_t)}{sep}"
                 f"mixed model {_p_is(p_mixed)}", fontsize=8 if not big else 11)
    ax.grid(axis="y", alpha=0.3)
    if big and ax.get_legend_handles_labels()[0]:      # no legend with nothing drawn
        ax.legend(fontsize=7, loc="best", framealpha=0.6)
    return fig


def _correlation(result, metric):
    """(r, p_r) of ``metric`` against the instructor score over the participants'
    means: ``stats``, else computed."""
    row = _stats_row(result, metric)
    if not _isnan(row.get("r")):
        return float(row["r"]), row.get("p_r", math.nan)
    from metrics.validity import correlate

    ok = _scatter_means(result.table, metric)
    try:
        c = correlate(ok["y"], ok["x"])
    except ValueError:
        return math.nan, math.nan
    return c["r"], c["p_r"]


def _scatter_means(table, metric):
    """Per labelled participant with both: the mean instructor score and the
    mean ``metric`` over their runs, as the statistics' correlation takes them
    (:func:`metrics.group_stats.group_statistics`); columns ``group, x, y``."""
    from metrics.group_stats import participant_means

    pm = participant_means(table, metric).set_index("participant")
    sc = table[["participant", "instructor_score"]].assign(
        instructor_score=lambda d: d["instructor_score"].astype(float)
    ).groupby("participant")["instructor_score"].mean()
    both = pm.join(sc, how="inner").dropna(subset=["value", "instructor_score"])
    return both.rename(columns={"instructor_score": "x", "value": "y"})[["group", "x", "y"]]


def _scatter_plot(result, metric, groups):
    """Instructor score (x) against one metric (y), as the thesis' figures 19
    and 21, one point per participant (their means over the sessions)."""
    plt = _pyplot()
    pm = _scatter_means(result.table, metric)
    fig, ax = plt.subplots(figsize=FIG_SIZE)
    for g in groups:
        sel = pm["group"] == g
        ax.scatter(pm.loc[sel, "x"], pm.loc[sel, "y"], color=_colour(g),
                   label=f"{_label(g)} (n = {int(sel.sum())} people)", s=30, zorder=3,
                   alpha=0.8)
    x, y = pm["x"].to_numpy(float), pm["y"].to_numpy(float)
    if len(x) >= 2 and np.ptp(x) > 0:
        k, c = np.polyfit(x, y, 1)
        xs = np.linspace(x.min(), x.max(), 2)
        ax.plot(xs, k * xs + c, color="k", lw=1.2, label="least squares")
    r, p = _correlation(result, metric)
    ax.set_title(f"Instructor score vs {metric}: R = {_num(r)}, {_p_is(p)}")
    ax.set_xlabel("instructor score (participant mean)")
    ax.set_ylabel(_axis_label(metric) + " (participant mean)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def _force_plot(result):
    """Mean force per 2 mm bin per group with confidence intervals, or a reason."""
    from metrics.forces import BIN_MM, FORCES, group_bins

    groups_of = {}
    if "file" in result.table:
        groups_of = dict(zip(result.table["file"].astype(str),
                             result.table["group"].fillna("").astype(str)))
    tabs, grp = [], []
    for f, tb in (result.force_tables or {}).items():
        g = groups_of.get(str(f), "") or tb.group
        if g:
            tabs.append(tb)
            grp.append(g)
    if not tabs:
        return None, "no force tables with a group"
    bs = group_bins(tabs, grp, bin_mm=BIN_MM, confidence=CONFIDENCE)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=FIG_SIZE)
    order = [g for g in GROUP_ORDER if g in bs.groups] + \
        [g for g in bs.groups if g not in GROUP_ORDER]
    shift = 0.12 * BIN_MM
    for q, g in enumerate(order):
        gi = bs.groups.index(g)
        x = bs.centers_mm + (q - (len(order) - 1) / 2) * shift
        m, lo, hi = bs.force_mean[gi], bs.force_lo[gi], bs.force_hi[gi]
        has = np.isfinite(m)
        if not has.any():
            continue
        err = np.vstack([np.where(np.isfinite(lo), m - lo, 0),
                         np.where(np.isfinite(hi), hi - m, 0)])
        runs = sum(1 for gg in grp if gg == g)
        ax.errorbar(x[has], m[has], yerr=err[:, has], fmt="o-", color=_colour(g), capsize=3,
                    ms=4, lw=1.3,
                    label=f"{_label(g)} ({runs} runs, {int(bs.n[gi].sum())} removals)")
    ax.set_xlabel(f"distance from the {clinical_name(bs.structure)} [mm] "
                  f"({BIN_MM:g} mm bins)")
    ax.set_ylabel("mean force [N]")
    ax.set_title(f"Force near the {clinical_name(bs.structure)}, {CONFIDENCE:.0%} CI per bin")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    note = (f"Force: {FORCES.get(bs.force, bs.force)}. Rows of all runs of a group are pooled "
            "per bin (as the thesis does); rows of one run are not independent, so the "
            "intervals are narrower than a per-run analysis would give.")
    return fig, note


# ------------------------------------------------------------------ sections
def _header(result, groups) -> str:
    t = result.table
    meta = dict(result.meta or {})
    out = ["<h1>Construct validity of the bonesim drilling metrics</h1>"]
    if _synthetic(result):
        out.append("<p class=\"notice\">SYNTHETIC TEST DATA: these runs were scripted by "
                   "behaviour models (bonesim cohort synth), not performed by people. The "
                   "numbers below test the pipeline; they say nothing about surgeons.</p>")
    from metrics.report_design import design_section

    out.append(design_section(result))
    out.append("<h2>1. Cohort</h2><table><tr><th class=\"l\">group</th><th>runs</th>"
               "<th>participants</th><th>failed runs</th><th>with instructor score</th></tr>")
    err = t["error"].fillna("").astype(str).str.len() > 0 if "error" in t else None
    for g in groups:
        sel = t["group"].fillna("") == g
        nerr = int((sel & err).sum()) if err is not None else 0
        nsc = int(t.loc[sel, "instructor_score"].astype(float).notna().sum())
        out.append(f"<tr><td class=\"l\">{_esc(_label(g))}</td><td>{int(sel.sum())}</td>"
                   f"<td>{t.loc[sel, 'participant'].nunique()}</td><td>{nerr}</td>"
                   f"<td>{nsc}</td></tr>")
    out.append(f"<tr><th class=\"l\">all</th><th>{len(t)}</th>"
               f"<th>{t['participant'].nunique()}</th>"
               f"<th>{int(err.sum()) if err is not None else 0}</th>"
               f"<th>{int(t['instructor_score'].astype(float).notna().sum())}</th></tr></table>")
    cases = sorted(str(c) for c in t["case"].dropna().unique() if str(c))
    out.append("<dl>")
    out.append(f"<dt>case</dt><dd>{_esc(', '.join(cases) or NA)}</dd>")
    out.append(f"<dt>structure (forces)</dt><dd>{_esc(result.structure)}</dd>")
    for k, v in meta.items():
        if k == "sessions" and isinstance(v, list):
            v = f"{len(v)} files"
        out.append(f"<dt>{_esc(k)}</dt><dd>{_esc(_num(v) if isinstance(v, float) else v)}</dd>")
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    out.append(f"<dt>report written</dt><dd>{_esc(now)}</dd></dl>")
    errors = list(result.errors or [])
    if errors:
        out.append(f"<div class=\"errors\"><b>Errors ({len(errors)})</b><ul>")
        out += [f"<li>{_esc(e)}</li>" for e in errors]
        out.append("</ul></div>")
    else:
        out.append("<p>Errors: none (every run loaded; every participant has a run).</p>")
    return "\n".join(out)


def _plotted_metrics(result) -> list:
    """Metrics with a finite value in some run: :data:`KEY_METRICS` first."""
    from metrics.cohort_result import METRIC_COLUMNS

    t = result.table
    has = [m for m in METRIC_COLUMNS if m in t and np.isfinite(t[m].astype(float)).any()]
    return [m for m in KEY_METRICS if m in has] + [m for m in has if m not in KEY_METRICS]


def _group_section(result, groups, figs) -> str:
    from metrics.cohort_result import METRIC_COLUMNS

    out = ["<h2>2. Scores by group</h2>",
           (f"<p>Each solid dot is one participant: the mean of their sessions, the unit "
           "every group test uses (jittered sideways); the faint small dots above and below "
           "it are that participant's sessions. The square and bars are the group mean of "
           f"the participants and its {CONFIDENCE:.0%} t confidence interval. Titles give the "
           "per-participant two-tailed t-test p-value after the design's correction across "
           "metrics (uncorrected for a metric outside the tests), and the mixed model's "
           "corrected group p-value over every run (n/a: not tested or not fitted).</p>")]
    metrics = _plotted_metrics(result)
    key = [m for m in metrics if m in KEY_METRICS]
    rest = [m for m in metrics if m not in KEY_METRICS]
    empty = [m for m in METRIC_COLUMNS if m not in metrics]
    for part in (key, rest):
        out.append("<div class=\"grid\">")
        for m in part:
            img = figs.fig(_group_plot(result, m, groups, m in KEY_METRICS), f"group_{m}",
                           f"{m} by group")
            out.append(f"<figure>{img}</figure>")
        out.append("</div>")
    if empty:
        out.append(f"<p class=\"note\">No values in any run (not plotted): "
                   f"{_esc(', '.join(empty))}.</p>")
    return "\n".join(out)


def _scatter_section(result, groups, figs) -> str:
    out = ["<h2>3. Instructor score against the metrics</h2>",
           ("<p>Each dot is one participant (the means of their sessions' instructor scores "
           "and metric); the line is the least-squares fit over the participants; R is "
           "Pearson's correlation of those means with its two-tailed p.</p>"
           "<div class=\"grid\">")]
    for m in SCATTER_METRICS:
        ok = result.table[["instructor_score", m]].astype(float).notna().all(axis=1) \
            if m in result.table else None
        if ok is None or ok.sum() < 2:
            out.append(f"<p class=\"note\">{_esc(m)}: fewer than two runs with both an "
                       "instructor score and a value; not plotted.</p>")
            continue
        img = figs.fig(_scatter_plot(result, m, groups), f"scatter_{m}",
                       f"instructor score against {m}")
        out.append(f"<figure>{img}</figure>")
    out.append("</div>")
    return "\n".join(out)


def _force_section(result, figs) -> str:
    out = [f"<h2>4. Force against distance to the {_esc(clinical_name(result.structure))}"
           "</h2>"]
    try:
        fig, note = _force_plot(result)
    except ValueError as exc:
        fig, note = None, f"not drawn: {exc}"
    if fig is None:
        out.append(f"<p class=\"note\">Not drawn: {_esc(note)}.</p>")
    else:
        out.append(f"<figure>{figs.fig(fig, 'forces', 'force against distance')}"
                   f"<figcaption>{_esc(note)}</figcaption></figure>")
    return "\n".join(out)


def _default_runs(table) -> list:
    """One run of each of :data:`GROUP_ORDER` that loaded (file order)."""
    ok = table["error"].fillna("").astype(str) == "" if "error" in table else \
        np.ones(len(table), bool)
    out = []
    for g in GROUP_ORDER:
        rows = table[ok & (table["group"].fillna("") == g)]
        if len(rows):
            out.append(str(rows["file"].iloc[0]))
    return out


def _visibility_section(result, runs, figs) -> str:
    out = ["<h2>5. Visibility at removal</h2>",
           ("<p>Removed voxels seen from the case camera, the bone not drawn: green when the "
           "voxel was visible from the eye when removed, red when other bone hid it "
           "(undercutting).</p><div class=\"grid\">")]
    runs = _default_runs(result.table) if runs is None else list(runs)
    if not runs:
        out.append("<p class=\"note\">No run to show.</p>")
    info = {}
    if "file" in result.table:
        for _, r in result.table.iterrows():
            info[str(r["file"])] = f"{r['participant']} ({_label(str(r['group'] or ''))})"
    with tempfile.TemporaryDirectory(prefix="bonesim_report_") as tmp:
        for q, run in enumerate(runs):
            name = str(getattr(run, "path", run))
            who = info.get(name, _name(name))
            try:
                from bonesim.session.reader import read_session
                from metrics.visibility import render_visibility

                s = run if hasattr(run, "header") else read_session(run)
                png = render_visibility(s, Path(tmp) / f"vis{q}.png", size=(640, 480))
                data = Path(png).read_bytes()
            except Exception as exc:  # noqa: BLE001  (no OpenGL, unreadable file, ...)
                out.append(f"<p class=\"note\">{_esc(_name(name))}: view not rendered "
                           f"({_esc(type(exc).__name__)}: {_esc(exc)}).</p>")
                continue
            img = figs.png(data, f"visibility_{q}_{Path(name).stem}", f"visibility of {who}")
            out.append(f"<figure>{img}<figcaption>{_esc(who)}: {_esc(_name(name))}"
                       "</figcaption></figure>")
    out.append("</div>")
    return "\n".join(out)


def _better(b) -> str:
    if _isnan(b):
        return NA
    b = int(b)
    return "higher" if b > 0 else "lower" if b < 0 else "neither"


def _stats_table(result, groups) -> str:
    """The statistics table (:func:`metrics.report_design.stats_section`),
    over the built-in metric columns and any extra ones the table holds."""
    from metrics.cohort_result import METRIC_COLUMNS
    from metrics.report_design import stats_section

    cols = dict(METRIC_COLUMNS)
    st = result.stats
    if st is not None and len(st) and "metric" in st:
        for r in st.to_dict("records"):
            cols.setdefault(r["metric"], (r.get("unit", ""), r.get("better", 0)))
    return stats_section(result, cols)


def _runs_table(result) -> str:
    from metrics.cohort_result import METRIC_COLUMNS, RUN_COLUMNS

    t = result.table
    extra = [c for c in t.columns if c not in RUN_COLUMNS and c not in METRIC_COLUMNS
             and c != "notes" and np.issubdtype(t[c].dtype, np.number)]
    cols = [c for c in RUN_COLUMNS if c in t] + [m for m in METRIC_COLUMNS if m in t] + extra
    out = [f"<details><summary>Every run ({len(t)} rows)</summary><table><tr>"]
    out += [f"<th class=\"l\">{_esc(c)}</th>" for c in cols]
    out.append("</tr>")
    for _, r in t.iterrows():
        bad = bool(str(r.get("error", "") or "").strip()) and not _isnan(r.get("error"))
        out.append("<tr class=\"err\">" if bad else "<tr>")
        for c in cols:
            v = r[c]
            if c == "file":
                out.append(f"<td class=\"l\" title=\"{_esc(v)}\">{_esc(_name(v))}</td>")
            elif c in METRIC_COLUMNS or c in extra or c in ("instructor_score", "session"):
                out.append(_cell(_esc(_num(v))))
            else:
                out.append(_cell(_esc("" if _isnan(v) else v), left=True))
        out.append("</tr>")
    out.append("</table></details>")
    return "\n".join(out)


def _nb_section(result) -> str:
    trained = result.nb_trained_on or {}
    out = [("<details><summary>Naive Bayes training sets (leave one participant out: "
           f"{len(trained)} runs scored)</summary>"),
           ("<p>Each run's score comes from a model trained on these runs only; none is by "
           "the scored run's participant.</p><table><tr><th class=\"l\">scored run</th>"
           "<th>trained on</th><th class=\"l\">training runs</th></tr>")]
    for f, train in trained.items():
        train = list(train)
        out.append(f"<tr><td class=\"l\" title=\"{_esc(f)}\">{_esc(_name(f))}</td>"
                   f"<td>{len(train)}</td><td class=\"l\">"
                   f"{_esc(', '.join(_name(x) for x in train))}</td></tr>")
    out.append("</table></details>")
    return "\n".join(out)


# ------------------------------------------------------------------ entry point
def write_report(result, path, *, visibility_runs=None, png_dir=None) -> Path:
    """Write a scored cohort as one self-contained HTML page (module docstring).

    Parameters
    ----------
    result : metrics.cohort_result.CohortResult
        The scored cohort.
    path : path
        HTML file to write (its folder is made).
    visibility_runs : sequence of path or Session, optional
        Runs whose visibility view to show (default: the first expert and
        the first novice run of ``result.table`` that loaded). A run that
        cannot be read or rendered (no offscreen OpenGL) gets a note instead.
    png_dir : path, optional
        Also write every embedded image there as a PNG (to look at the
        plots without a browser).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        If ``result.table`` lacks the run columns.
    """
    from metrics.cohort_result import RUN_COLUMNS

    t = result.table
    missing = [c for c in RUN_COLUMNS if c not in getattr(t, "columns", ())]
    if missing:
        raise ValueError(f"result.table lacks the columns {missing}")
    figs = _Figures(png_dir)
    groups = _groups(t)
    from metrics.report_design import (agreement_section, classifier_section,
                                       instructor_section)

    body = [_header(result, groups), _group_section(result, groups, figs),
            _scatter_section(result, groups, figs), _force_section(result, figs),
            _visibility_section(result, visibility_runs, figs),
            _stats_table(result, groups), classifier_section(result, figs),
            agreement_section(result, figs), instructor_section(result, figs),
            "<h2>7. Runs</h2>", _runs_table(result),
            _nb_section(result)]
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<title>bonesim cohort report</title>"
            f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page, encoding="utf-8")
    return path
