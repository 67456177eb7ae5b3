"""The parts of the cohort report a reviewer reads first and last: the
study's design and provenance, the statistics table with its corrections,
the Naive Bayes ROC and the test-retest agreement (:mod:`metrics.report`
assembles the page; these return HTML fragments).

Every string from the data is escaped; a missing number reads "n/a".
"""
from __future__ import annotations

import html
import math

import numpy as np

__all__ = ["design_section", "stats_section", "classifier_section", "agreement_section",
           "instructor_section"]

_NA = "n/a"


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def _isnan(x) -> bool:
    try:
        return x is None or math.isnan(float(x))
    except (TypeError, ValueError):
        return False


def _num(x, digits: int = 3) -> str:
    if _isnan(x):
        return _NA
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return str(int(v)) if v == int(v) and abs(v) < 1e6 else f"{v:.{digits}g}"


def _p(x) -> str:
    if _isnan(x):
        return _NA
    return "< 0.001" if float(x) < 0.001 else f"{float(x):.3f}"


def design_section(result) -> str:
    """"Design and provenance": participants and sessions per group, the unit
    of analysis, primary metrics and corrections, metrics left out and why,
    and where the result came from."""
    t = result.table
    d = dict(getattr(result, "design", None) or {})
    prov = dict(getattr(result, "provenance", None) or {})
    out = ["<h2>Design and provenance</h2>"]
    if not d:
        out.append("<p class=\"note\">No declared design recorded with this result: the "
                   "statistics below are per run and uncorrected.</p>")
    else:
        lab = t[t["group"].isin(["expert", "novice"])] if "group" in t else t.iloc[:0]
        per = lab.groupby(["group", "participant"]).size() if len(lab) else None
        out.append("<table><tr><th class=\"l\">group</th><th>participants</th>"
                   "<th>runs</th><th>sessions per participant</th></tr>")
        for g in ("expert", "novice"):
            if per is not None and g in per.index.get_level_values(0):
                n = per.loc[g]
                out.append(f"<tr><td class=\"l\">{g}</td><td>{len(n)}</td><td>{int(n.sum())}"
                           f"</td><td>{int(n.min())}&ndash;{int(n.max())}</td></tr>")
        out.append("</table>")
        unit = d.get("unit", "participant")
        out.append("<dl>")
        out.append(f"<dt>unit of analysis</dt><dd>{_esc(unit)}"
                   + (" (each participant's mean over their sessions; a mixed model with a "
                      "random intercept per participant uses every run)"
                      if unit == "participant" else
                      " (every run as if independent: repeated sessions inflate n)")
                   + "</dd>")
        out.append(f"<dt>primary metrics</dt><dd>{_esc(', '.join(d.get('primary', [])))}, "
                   f"corrected together by {_esc(d.get('primary_correction'))}</dd>")
        out.append(f"<dt>other metrics</dt><dd>corrected together by "
                   f"{_esc(d.get('secondary_correction'))} (Holm and Benjamini-Hochberg "
                   "both reported)</dd>")
        out.append(f"<dt>significance level</dt><dd>{_esc(_num(d.get('alpha')))} after "
                   "correction</dd>")
        out.append(f"<dt>close to the structure</dt><dd>within {_esc(_num(d.get('close_mm')))}"
                   " mm (force_close_n, tool_speed_close_mm_s, exceedances_close)</dd>")
        out.append(f"<dt>design file</dt><dd>{_esc(d.get('source', _NA))}</dd></dl>")
    ex = dict(getattr(result, "excluded", None) or {})
    if ex:
        out.append("<p><b>Not tested</b> (and why):</p><ul>")
        out += [f"<li><code>{_esc(m)}</code>: {_esc(r)}</li>" for m, r in ex.items()]
        out.append("</ul>")
    if prov:
        out.append("<p><b>Provenance</b></p><dl>")
        syn = prov.get("synthesis") or {}
        items = [("bonesim version", prov.get("bonesim_version")),
                 ("runs recorded with", ", ".join(prov.get("recorded_with") or []) or _NA),
                 ("case", "; ".join(f"{c.get('name')} sha256 {c.get('sha256')}"
                                    for c in prov.get("case") or []) or _NA),
                 ("burrs", "; ".join(f"{b.get('name')} sha256 {b.get('sha256')}"
                                     for b in prov.get("burrs") or []) or _NA),
                 ("participants file", f"{prov.get('participants_file')} sha256 "
                                       f"{prov.get('participants_sha256')}"),
                 ("synthesis seed", syn.get("seed", _NA) if syn else "not synthetic"),
                 ("instructor ratings", f"{prov.get('ratings_file')} sha256 "
                                        f"{prov.get('ratings_sha256')}"
                  if prov.get("ratings_file") else "none given"),
                 ("command", prov.get("command")), ("created", prov.get("created"))]
        out += [f"<dt>{_esc(k)}</dt><dd>{_esc(v if v is not None else _NA)}</dd>"
                for k, v in items]
        out.append("</dl>")
    return "\n".join(out)


def stats_section(result, columns) -> str:
    """"6. Statistics of every metric": the tests, corrections, effect sizes,
    classifier AUC, mixed model and correlations; a cell is highlighted where
    the metric differs after its family's correction."""
    st = result.stats
    rows = {r["metric"]: r for r in st.to_dict("records")} if st is not None and len(st) \
        and "metric" in st else {}
    unit = (getattr(result, "design", None) or {}).get("unit", "run")
    head = ["metric", "unit", "better", "family", "expert n", "expert mean", "expert sd",
            "novice n", "novice mean", "novice sd", "t", "p (t)", "p corrected", "U",
            "p (U)", "d [95% CI]", "AUC [95% CI]", "mixed: novice - expert", "p (mixed)",
            "p mixed corrected", "session effect", "p (session)", "rho", "p (rho)", "R",
            "p (R)"]
    out = ["<h2>6. Statistics of every metric</h2>",
           f"<p>Unit: {_esc(unit)}. Two-tailed Student t-test and Mann-Whitney U between "
           "groups on the unit's values; p corrected within the metric's family (primary: "
           "declared correction, other: false discovery rate; the correction is in the "
           "cell's tooltip); Cohen's d (expert minus novice) with its interval, undefined "
           "when a group has no variance (the reason in the tooltip); AUC of the metric as a "
           "classifier of the groups (oriented by its better direction) with Newcombe's "
           "interval; the mixed model's group and per-session effects; Spearman's rho and "
           "Pearson's R against the instructor score. Highlighted: corrected p &lt; "
           f"{_esc(_num((getattr(result, 'design', None) or {}).get('alpha', 0.05)))}.</p>",
           "<table><tr>"]
    left = ' class="l"'
    out += [f"<th{left if q == 0 else ''}>{_esc(h)}</th>" for q, h in enumerate(head)]
    out.append("</tr>")
    for m, (u, better) in columns.items():
        r = rows.get(m, {})
        sig = bool(r.get("significant")) if not _isnan(r.get("significant")) else False
        if not r and "p_t" not in r:
            sig = False
        msig = bool(r.get("mixed_significant")) if not _isnan(r.get("mixed_significant")) \
            else False

        def cell(v, hl=False, title=None):
            t = f' title="{_esc(title)}"' if title else ""
            c = ' class="sig"' if hl else ""
            return f"<td{c}{t}>{_esc(v)}</td>"

        d = _num(r.get("d"))
        if d != _NA:
            d += f" [{_num(r.get('d_lo'))}, {_num(r.get('d_hi'))}]"
        auc = _num(r.get("auc"))
        if auc != _NA:
            auc += f" [{_num(r.get('auc_lo'))}, {_num(r.get('auc_hi'))}]"
        cells = [f"<td class=\"l\">{_esc(m)}</td>", cell(r.get("unit", u) or "-"),
                 cell({1: "higher", -1: "lower"}.get(int(better), "neither")),
                 cell(r.get("family", _NA) if r else "not tested")]
        for g in ("expert", "novice"):
            for k in ("n", "mean", "sd"):
                cells.append(cell(_num(r.get(f"{g}_{k}"))))
        cells += [cell(_num(r.get("t"))), cell(_p(r.get("p_t"))),
                  cell(_p(r.get("p_t_adj")), sig, r.get("correction")),
                  cell(_num(r.get("u"))), cell(_p(r.get("p_u")), False, r.get("u_method")),
                  cell(d, False, r.get("d_note") or None), cell(auc, False,
                                                               r.get("auc_expert_is")),
                  cell(_num(r.get("mixed_group_effect"))),
                  cell(_p(r.get("mixed_p_group")), False, r.get("mixed_note") or None),
                  cell(_p(r.get("p_mixed_adj")), msig, r.get("correction")),
                  cell(_num(r.get("mixed_session_effect"))), cell(_p(r.get("mixed_p_session"))),
                  cell(_num(r.get("rho"))), cell(_p(r.get("p_rho"))),
                  cell(_num(r.get("r"))), cell(_p(r.get("p_r")))]
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def classifier_section(result, figs) -> str:
    """ROC curves of the leave-one-participant-out Naive Bayes scores."""
    cl = dict(getattr(result, "classifiers", None) or {})
    out = ["<h2>Naive Bayes as a classifier</h2>"]
    if not cl:
        out.append("<p class=\"note\">No ROC: the Naive Bayes scores need participants of "
                   "both groups.</p>")
        return "\n".join(out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    for k, r in cl.items():
        ax.step(r["fpr"], r["tpr"], where="post", lw=2,
                label=f"{k}: AUC {r['auc']:.3f} [{r['auc_ci'][0]:.3f}, {r['auc_ci'][1]:.3f}]")
    ax.plot([0, 1], [0, 1], ":", color="#888")
    ax.set_xlabel("false positive rate (novices called expert)")
    ax.set_ylabel("true positive rate (experts called expert)")
    ax.set_title("ROC, leave one participant out\n(participants' mean scores)", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out.append("<p>Each participant's mean score over their runs, every score from a model "
               "trained without that participant. Summed: the log-likelihood ratio over the "
               "removed voxels [nats]; per voxel: divided by the voxels removed (technique, "
               "not volume). Interval: Newcombe (2006).</p>")
    out.append(f"<figure>{figs.fig(fig, 'roc_naive_bayes', 'Naive Bayes ROC')}</figure>")
    return "\n".join(out)


def agreement_section(result, figs) -> str:
    """Test-retest of the primary metrics: ICC(2,1) and Bland-Altman plots."""
    ag = dict(getattr(result, "agreement", None) or {})
    out = ["<h2>Test-retest agreement</h2>"]
    if not ag:
        out.append("<p class=\"note\">Not computed: needs at least three participants with "
                   "two sessions or more.</p>")
        return "\n".join(out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.append("<p>Each participant's first against last session. ICC(2,1): two-way random "
               "effects, absolute agreement, single measurement (Shrout &amp; Fleiss), with "
               "its interval; Bland-Altman: bias and 95 % limits of agreement (last minus "
               "first session; a learning effect shows as a bias).</p><table><tr>"
               "<th class=\"l\">metric</th><th>participants</th><th>ICC(2,1) [95% CI]</th>"
               "<th>bias [95% CI]</th><th>limits of agreement</th></tr>")
    plots = []
    for m, r in ag.items():
        i, b = r.get("icc", {}), r["bland_altman"]
        ic = _num(i.get("icc2_1"))
        if ic != _NA:
            ic += f" [{_num(i['icc2_1_ci'][0])}, {_num(i['icc2_1_ci'][1])}]"
        out.append(f"<tr><td class=\"l\">{_esc(m)}</td><td>{r['participants']}</td>"
                   f"<td>{_esc(ic)}</td><td>{_esc(_num(b['bias']))} "
                   f"[{_esc(_num(b['bias_ci'][0]))}, {_esc(_num(b['bias_ci'][1]))}]</td>"
                   f"<td>{_esc(_num(b['loa'][0]))} to {_esc(_num(b['loa'][1]))}</td></tr>")
        fig, ax = plt.subplots(figsize=(4.2, 3.4))
        ax.scatter(b["mean"], b["diff"], s=14, color="#444")
        for y, ls in ((b["bias"], "-"), (b["loa"][0], "--"), (b["loa"][1], "--")):
            ax.axhline(y, ls=ls, color="#d62728" if ls == "-" else "#888")
        ax.set_xlabel("mean of the two sessions")
        ax.set_ylabel("last minus first")
        ax.set_title(f"Bland-Altman: {m}", fontsize=9)
        fig.tight_layout()
        plots.append(f"<figure>{figs.fig(fig, f'bland_altman_{m}', f'Bland-Altman {m}')}"
                     "</figure>")
    out.append("</table><div class=\"grid\">" + "".join(plots) + "</div>")
    return "\n".join(out)


def _icc_text(i: dict) -> str:
    ic = _num(i.get("icc2_1"))
    if ic != _NA:
        ic += f" [{_num(i['icc2_1_ci'][0])}, {_num(i['icc2_1_ci'][1])}]"
    return ic


def instructor_section(result, figs) -> str:
    """Instructor scores (``--ratings``): ICC(2,1) between the raters, and of
    the simulator's score against their mean with a Bland-Altman plot."""
    ins = dict(getattr(result, "instructors", None) or {})
    out = ["<h2>Agreement with the instructors</h2>"]
    if not ins:
        out.append("<p class=\"note\">No instructor ratings given (bonesim metrics cohort "
                   "--ratings CSV with the columns participant, session, rater, score).</p>")
        return "\n".join(out)
    br, ag = ins["between_raters"], ins["against"]
    out.append(f"<p>Ratings: {_esc(ins['file'])} (SHA-256 {_esc(str(ins['sha256'])[:16])}...). "
               "ICC(2,1): two-way random effects, absolute agreement, single rater "
               "(Shrout &amp; Fleiss), with its 95 % interval. Each run scored is one "
               "target.</p><table><tr><th class=\"l\">comparison</th><th>runs</th>"
               "<th>ICC(2,1) [95% CI]</th><th>bias [95% CI]</th><th>limits of agreement</th>"
               "<th class=\"l\">note</th></tr>")
    note = br.get("note", "")
    if br.get("runs_left_out"):
        note = "; ".join(x for x in (note, f"{br['runs_left_out']} run(s) not scored by "
                                     "every rater, left out") if x)
    out.append(f"<tr><td class=\"l\">between the raters ({_esc(', '.join(br['raters']))})"
               f"</td><td>{br['runs']}</td><td>{_esc(_icc_text(br.get('icc', {})))}</td>"
               f"<td></td><td></td><td class=\"l\">{_esc(note)}</td></tr>")
    b = ag.get("bland_altman")
    bias = loa = ""
    if b:
        bias = f"{_num(b['bias'])} [{_num(b['bias_ci'][0])}, {_num(b['bias_ci'][1])}]"
        loa = f"{_num(b['loa'][0])} to {_num(b['loa'][1])}"
    out.append(f"<tr><td class=\"l\">{_esc(ag['metric'])} (simulator) against the raters' "
               f"mean</td><td>{ag['runs']}</td><td>{_esc(_icc_text(ag.get('icc', {})))}</td>"
               f"<td>{_esc(bias)}</td><td>{_esc(loa)}</td>"
               f"<td class=\"l\">{_esc(ag.get('note', ''))}</td></tr></table>")
    if b:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(4.2, 3.4))
        ax.scatter(b["mean"], b["diff"], s=14, color="#444")
        for y, ls in ((b["bias"], "-"), (b["loa"][0], "--"), (b["loa"][1], "--")):
            ax.axhline(y, ls=ls, color="#d62728" if ls == "-" else "#888")
        ax.set_xlabel("mean of simulator and instructors")
        ax.set_ylabel("simulator minus instructors")
        ax.set_title(f"Bland-Altman: {ag['metric']} vs instructors", fontsize=9)
        fig.tight_layout()
        img = figs.fig(fig, "bland_altman_instructors",
                       "Bland-Altman simulator against instructors")
        out.append(f"<div class=\"grid\"><figure>{img}</figure></div>")
    return "\n".join(out)


def finite(v) -> bool:
    """True for a finite number."""
    try:
        return bool(np.isfinite(float(v)))
    except (TypeError, ValueError):
        return False
