"""Handlers of the research commands of ``bonesim`` (``bonesim cohort ...``).

``bonesim``'s command line (:mod:`bonesim.cli.research` builds the arguments)
names these handlers by module path and imports them only when run, so the
simulator never imports the metrics.
"""
from __future__ import annotations

import sys

import numpy as np

from bonesim.cli.output import print_json
from bonesim.io.anatomy import clinical_name

__all__ = ["cmd_cohort_synth", "cmd_metrics_run", "cmd_metrics_cohort", "cmd_metrics_limits",
           "cmd_metrics_view", "cmd_metrics_progress", "cmd_metrics_export"]


def cmd_cohort_synth(args) -> int:
    """``bonesim cohort synth``: record a synthetic cohort (:mod:`metrics.synth`)."""
    from bonesim.errors import BonesimError
    from bonesim.progress import ProgressBar
    from metrics.synth import BEHAVIOURS_FILE, PARTICIPANTS_CSV, synth_cohort

    sessions = getattr(args, "sessions", 1)
    bar = ProgressBar(max((args.experts + args.novices) * max(sessions, 1), 1), "recording")
    try:
        paths = synth_cohort(args.out, args.experts, args.novices, seed=args.seed,
                             case=args.case, duration_s=args.duration, sessions=sessions,
                             behaviours=getattr(args, "behaviours", None)
                             or BEHAVIOURS_FILE,
                             progress=lambda done, _n: bar.update(done))
    except ValueError as exc:
        raise BonesimError(f"cohort synth: {exc}") from None
    bar.close()
    out = {"sessions": [str(p) for p in paths],
           "participants": str(paths[0].parent / PARTICIPANTS_CSV),
           "synthetic": True}
    if args.json:
        print_json(out)
    else:
        print(f"{len(paths)} synthetic runs ({args.experts} expert-like, {args.novices} "
              f"novice-like, {sessions} session(s) each, {args.duration:g} s per run, seed "
              f"{args.seed}) in {paths[0].parent}; participants in {out['participants']}",
              file=sys.stdout)
    return 0


def _fmt(x, unit="", digits=3):
    return "n/a" if x is None else f"{x:.{digits}g}{unit}"


def cmd_metrics_run(args) -> int:
    """``bonesim metrics run``: every metric of one run (:mod:`metrics.run`)."""
    from bonesim.session.reader import damage_notice, read_session
    from metrics.run import run_metrics

    s = read_session(args.file)
    line = damage_notice(s)
    if line:
        print(line, file=sys.stderr)
    status = 0 if s.damage is None else 1        # scored on a damaged file's readable part
    res = run_metrics(s, experts=args.expert or (), force_profile=args.force_profile,
                      structure=args.structure)
    if args.json:
        print_json(res)
        return status
    r, v, c = res["run"], res["visibility"], res["conduct"]
    print(f"{r['file']}: {r['participant'] or '(no participant)'}, case {r['case']}, "
          f"{r['duration_s']:.1f} s, {r['removed_voxels']} voxels removed")
    print(f"visibility: {_fmt(v['visible_fraction'])} of removals visible "
          f"({v['hidden']} hidden)")
    f = res["forces"]
    if "skipped" in f:
        print(f"forces: {f['skipped']}")
    else:
        print(f"forces near the {clinical_name(f['structure'])}: {f['rows']} removals "
              f"within 30 mm, mean {_fmt(f['mean_force_n'], ' N')}")
    for name, e in res["exposure"].items():
        print(f"exposure {clinical_name(name)}: "
              + ", ".join(f"{_fmt(val)} {k.replace('_', ' ')}"
                          for k, val in e.items() if k.startswith("under")))
    st = c["strokes"]
    print(f"strokes: {st['strokes']}, plunge {_fmt(st['mean_plunge'])}, straightness "
          f"{_fmt(st['mean_straightness'])}")
    hurt = {n: v for n, v in c["contacts"].items() if v["injuries"] or v["contacts"]}
    print("contacts: " + (", ".join(f"{clinical_name(n)} {v['contacts']} contact(s) "
                                    f"{v['injuries']} "
                                    f"injur{'y' if v['injuries'] == 1 else 'ies'}"
                                    for n, v in hurt.items()) or "none"))
    if "final_product" in res:
        m = res["final_product"]["mean"]
        print(f"final product vs {len(res['final_product']['per_expert'])} expert run(s): "
              f"Dice {_fmt(m['dice'])}, mean distance {_fmt(m['mean_mm'], ' mm')}")
    if "exceedances" in res:
        e = res["exceedances"]
        near = clinical_name(e["structure"])
        print(f"above the experts' limits near the {near} ({e['percentile']:g}th "
              f"percentile per 2 mm bin): force {e['count']['force_n']} time(s), speed "
              f"{e['count']['speed_rpm']} time(s), closer than any expert "
              f"({_fmt(e['closest_mm'], ' mm')}) {e['count']['approach_mm']} time(s)")
        for w in e["worst"]:
            unit, f = {"force_n": (" N", ".3f"), "approach_mm": (" mm", ".2f")}.get(
                w["quantity"], (" rpm", ",.0f"))
            print(f"  at {w['t_s']:.3f} s, {w['distance_mm']:.1f} mm from the {near}, burr at "
                  f"({', '.join(f'{v:.1f}' for v in w['pos_mm'])}) mm: "
                  f"{w['value']:{f}}{unit} against {w['limit']:{f}}{unit} "
                  f"(+{w['excess']:{f}}{unit})")
    if "alignment" in res:
        a = res["alignment"]
        print(f"force profile: residual {_fmt(a['rms_n'], ' N')} after alignment "
              f"({_fmt(a['unaligned_rms_n'], ' N')} before)")
    for ln in res.get("assessment", {}).get("checklist", []):
        print(ln)
    return status


def cmd_metrics_limits(args) -> int:
    """``bonesim metrics limits``: learn force limits from expert runs and write
    them for the window's live warnings (:func:`metrics.forces.expert_limits`)."""
    from bonesim.errors import BonesimError
    from bonesim.physics.force_limits import save_limits
    from metrics.cohort import find_sessions, read_participants
    from metrics.forces import expert_limits

    paths = find_sessions(args.sessions)
    table = read_participants(args.participants) if args.participants else None
    try:
        lim = expert_limits(paths, table, structure=args.structure,
                            percentile=args.percentile)
    except ValueError as exc:
        raise BonesimError(f"metrics limits: {exc}") from None
    save_limits(args.out, lim)
    have = int(np.count_nonzero(np.isfinite(lim.force_n)))
    out = {"limits": str(args.out), "structure": lim.structure, "case": lim.case,
           "experts": len(lim.source), "bins_with_limit": have, "bins": len(lim.force_n),
           "closest_mm": float(lim.closest_mm) if np.isfinite(lim.closest_mm) else None}
    if args.json:
        print_json(out)
    else:
        print(f"{args.out}: force and speed limits near the {clinical_name(lim.structure)} "
              f"({lim.percentile:g}th "
              f"percentile, {have} of {len(lim.force_n)} bins of "
              f"{lim.edges_mm[1] - lim.edges_mm[0]:g} mm; closer than "
              f"{_fmt(out['closest_mm'], ' mm')} in a bin without one) from "
              f"{len(lim.source)} expert run(s) of case {lim.case!r}; use it with bonesim run "
              "--force-limits")
    return 0


def cmd_metrics_view(args) -> int:
    """``bonesim metrics view``: a run's removals coloured by visibility, in a
    window to turn about (or to a PNG without a display or with ``--png``)."""
    import os

    from bonesim.session.reader import damage_notice, read_session
    from metrics.visibility import render_visibility, show_visibility

    s = read_session(args.file)
    line = damage_notice(s)
    if line:
        print(line, file=sys.stderr)
    size = tuple(args.size) if args.size else (1024, 768)
    structures = args.structure or None
    display = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if args.png or not display:
        png = args.png or "visibility.png"
        if not display and not args.png:
            print(f"bonesim: no display found; writing the view to {png} instead",
                  file=sys.stderr)
        try:
            out = render_visibility(s, png, structures, size)
        except ValueError as exc:
            from bonesim.errors import BonesimError

            raise BonesimError(f"metrics view: {exc}") from None
        print(f"wrote {out}")
        return 0
    try:
        show_visibility(s, structures, size, frames=args.frames)
    except ValueError as exc:
        from bonesim.errors import BonesimError

        raise BonesimError(f"metrics view: {exc}") from None
    return 0


def _write_report(result, path) -> str:
    try:
        from metrics.report import write_report
    except ImportError:
        return "report: metrics.report is not available"
    write_report(result, path)
    return f"report: {path}"


def _instructor_summary(ins: dict) -> dict:
    """``instructors``: the ICCs and the bias in brief (empty without ratings)."""
    if not ins:
        return {}
    br, ag = ins["between_raters"], ins["against"]
    out = {"raters": br["raters"], "between_raters_runs": br["runs"]}
    if "icc" in br:
        out["between_raters_icc2_1"] = br["icc"]["icc2_1"]
        out["between_raters_icc2_1_ci"] = br["icc"]["icc2_1_ci"]
    out.update(against=ag["metric"], against_runs=ag["runs"])
    if "icc" in ag:
        out["against_icc2_1"] = ag["icc"]["icc2_1"]
        out["against_icc2_1_ci"] = ag["icc"]["icc2_1_ci"]
    if "bland_altman" in ag:
        out["against_bias"] = ag["bland_altman"]["bias"]
        out["against_loa"] = ag["bland_altman"]["loa"]
    notes = [x for x in (br.get("note"), ag.get("note")) if x]
    if notes:
        out["notes"] = notes
    return {"instructors": out}


def cmd_metrics_cohort(args) -> int:
    """``bonesim metrics cohort``: score a cohort (:mod:`metrics.cohort`)."""
    from bonesim.progress import ProgressBar
    from metrics.cohort import find_sessions, score_cohort, write_table

    if getattr(args, "ratings", None):      # a bad file: one line before anything else
        from metrics.participants import read_participants
        from metrics.raters import read_ratings

        read_ratings(args.ratings, read_participants(args.participants))
    n = len(find_sessions(args.sessions))
    bar = ProgressBar(n, "scoring")
    res = score_cohort(args.sessions, args.participants, scheduler=args.scheduler,
                       workers=args.workers, structure=args.structure,
                       progress=lambda done, _n: bar.update(done),
                       design=getattr(args, "design", None),
                       command=_command(args), ratings=getattr(args, "ratings", None),
                       ratings_against=getattr(args, "ratings_against", "assess_total"),
                       cache=getattr(args, "cache", None))
    bar.close()
    for line in res.errors:
        print(line, file=sys.stderr)
    out = {}
    if args.out:
        out["table"] = str(write_table(res, args.out))
    if getattr(args, "exports", None):
        from metrics.exports import export_cohort

        out["exports"] = export_cohort(res, args.exports)
    if args.report:
        out["report"] = _write_report(res, args.report)
    tb, st = res.table, res.stats
    sig = st[st["significant"].astype(bool)] if len(st) else st
    summary = {"runs": int(len(tb)), "scored": int((tb["error"] == "").sum()),
               "failed": int((tb["error"] != "").sum()), "errors": list(res.errors),
               "case": res.meta.get("case"), "scheduler": res.meta["scheduler"],
               "workers": res.meta["workers"], "wall_s": round(res.meta["wall_s"], 2),
               "unit": res.design.get("unit"), "stats_s": round(res.meta["stats_s"], 3),
               "significant": [{"metric": r.metric, "family": r.family,
                                "expert_mean": _num(r.expert_mean),
                                "novice_mean": _num(r.novice_mean), "p_t": _num(r.p_t),
                                "p_adjusted": _num(r.p_t_adj), "correction": r.correction,
                                "d": _num(r.d), "p_mixed_adjusted": _num(r.p_mixed_adj)}
                               for r in sig.itertuples()],
               "excluded": dict(res.excluded),
               "naive_bayes_auc": {k: {"auc": v["auc"], "ci": v["auc_ci"]}
                                   for k, v in res.classifiers.items()},
               **_instructor_summary(res.instructors), **out}
    if args.json:
        print_json(summary)
        return 0
    print(f"{summary['scored']} of {summary['runs']} runs scored ({summary['failed']} "
          f"failed) on case {summary['case']}, {res.meta['scheduler']} with "
          f"{res.meta['workers']} worker(s), {summary['wall_s']:.1f} s")
    unit = f"per {summary['unit']}" if summary["unit"] else ""
    if summary["significant"]:
        print(f"metrics that differ between experts and novices ({unit} t-test, "
              "corrected p < 0.05):")
        for r in summary["significant"]:
            print(f"  {r['metric']} ({r['family']}): expert {_fmt(r['expert_mean'])}, novice "
                  f"{_fmt(r['novice_mean'])}, p {_fmt(r['p_t'], digits=2)}, {r['correction']} "
                  f"{_fmt(r['p_adjusted'], digits=2)}, d {_fmt(r['d'])}")
    else:
        print(f"no metric differs between experts and novices ({unit}, corrected p < 0.05)")
    for k, v in summary["naive_bayes_auc"].items():
        print(f"{k}: leave-one-participant-out AUC {_fmt(v['auc'])} "
              f"[{_fmt(v['ci'][0])}, {_fmt(v['ci'][1])}]")
    ins = summary.get("instructors")
    if ins:
        if "between_raters_icc2_1" in ins:
            lo, hi = ins["between_raters_icc2_1_ci"]
            print(f"between {len(ins['raters'])} raters over {ins['between_raters_runs']} runs: "
                  f"ICC(2,1) {_fmt(ins['between_raters_icc2_1'])} [{_fmt(lo)}, {_fmt(hi)}]")
        if "against_icc2_1" in ins:
            lo, hi = ins["against_icc2_1_ci"]
            print(f"{ins['against']} against the instructors over {ins['against_runs']} runs: "
                  f"ICC(2,1) {_fmt(ins['against_icc2_1'])} [{_fmt(lo)}, {_fmt(hi)}], bias "
                  f"{_fmt(ins['against_bias'])} (limits {_fmt(ins['against_loa'][0])} to "
                  f"{_fmt(ins['against_loa'][1])})")
        for n in ins.get("notes", []):
            print(f"instructor scores: {n}")
    for k in ("table", "report"):
        if k in out:
            print(out[k] if k == "report" else f"table: {out[k]}")
    if "exports" in out:
        print("exports: " + ", ".join(out["exports"].values()))
    return 0


def _command(args) -> str:
    """The command line that ran, for the provenance."""
    import shlex

    return shlex.join(["bonesim", *getattr(args, "argv", sys.argv[1:])])


def cmd_metrics_progress(args) -> int:
    """``bonesim metrics progress``: learning curves (:mod:`metrics.progress`)."""
    from bonesim.errors import BonesimError
    from bonesim.progress import ProgressBar
    from metrics.cohort import find_sessions, metric_columns, score_cohort
    from metrics.progress import draw_progress

    from metrics.run_cache import default_cache_dir

    cache = None if args.no_cache else (args.cache or default_cache_dir())
    bar = ProgressBar(len(find_sessions(args.sessions)), "scoring")
    res = score_cohort(args.sessions, args.participants, workers=args.workers,
                       progress=lambda done, _n: bar.update(done), cache=cache)
    bar.close()
    if cache is not None:
        print(f"{res.meta['cached']} of {len(res.table)} runs read from the cache {cache}",
              file=sys.stderr)
    for line in res.errors:
        print(line, file=sys.stderr)
    try:
        out = draw_progress(res.table, args.out, args.metric, metric_columns())
    except ValueError as exc:
        raise BonesimError(f"metrics progress: {exc}") from None
    if args.json:
        print_json(out, default=_num)
        return 0
    print(f"wrote {out['png']}")
    for m, imp in out["metrics"].items():
        print(f"  {m}: mean change per session (oriented, + is better): novices "
              f"{_fmt(imp['novice'])}, experts {_fmt(imp['expert'])}; "
              f"{_fmt(imp['improving'] * 100 if imp['improving'] == imp['improving'] else None)}"
              " % of novices improve")
    return 0


def cmd_metrics_export(args) -> int:
    """``bonesim metrics export``: a run's visibility NRRD and removals
    Parquet with provenance (:func:`metrics.exports.export_run`)."""
    from metrics.exports import export_run

    out = export_run(args.file, args.out, participants=args.participants,
                     command=_command(args))
    if args.json:
        print_json(out)
    else:
        print(f"visibility: {out['visibility']}\nremovals: {out['removals']}")
    return 0


def _num(x):
    import math

    x = float(x)
    return None if math.isnan(x) else x
