"""``bonesim assess RUN.h5``: a run's final product, item by item, and the
checklist printed at the end of ``bonesim run``.

The assessment itself is research code (:mod:`metrics.assessment`, beside
the package); it is imported by name only when a command asks for it
(:func:`bonesim.cli.research.research_module`: ``bonesim`` never imports
``metrics``), so a machine that only drills never loads it before the end of
a run.
"""
from __future__ import annotations

import sys

from bonesim.cli.output import print_json

__all__ = ["assess_parsers", "cmd_assess", "checklist_of_grid", "print_checklist"]


def assess_parsers(sub, _lazy) -> None:
    """Add ``bonesim assess`` to the subcommands ``sub``; ``_lazy(module,
    name)`` makes a handler imported only when run."""
    s = sub.add_parser("assess", help="score a recorded run's final product item by item "
                       "(saucerization, tegmen, sinus, antrum, canal wall, injuries...) with "
                       "one sentence of advice each; --png draws the cavity with each item "
                       "marked")
    s.add_argument("file", help="session file (.h5)")
    s.add_argument("--png", metavar="OUT.png", help="draw the cavity from the surgeon's view "
                   "with each item's region (green done, amber partial, red missed or "
                   "violated)")
    s.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                   help="picture size [px] (default 1280 960)")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=_lazy("bonesim.cli.assess", "cmd_assess"))


def cmd_assess(args) -> int:
    """Handler of ``bonesim assess``."""
    from bonesim.cli.research import research_module
    from bonesim.errors import BonesimError
    from bonesim.session.reader import damage_notice, read_session

    m = research_module("metrics.assessment", "bonesim assess")

    s = read_session(args.file)
    line = damage_notice(s)
    if line:
        print(line, file=sys.stderr)
    size = tuple(args.size) if args.size else (1280, 960)
    if min(size) < 16 or max(size) > 8192:
        raise BonesimError(f"picture size must be 16..8192 px, got {size[0]} x {size[1]}",
                           field="--size")
    model = s.load_model()
    case = model.case
    d0, lab0 = model.grid.to_dense()
    present = m.final_present(s, model)
    a = m.assess_tissue(lab0, present, model.spacing_mm, model.grid.origin_mm,
                      model.structures, case.landmarks, case.camera.eye_mm, density0=d0,
                      case=model.name)
    out = a.as_dict()
    out["file"] = str(s.path)
    if args.png:
        from bonesim.render.assessment_view import assessment_picture

        who = s.header.get("participant") or ""
        title = (f"{model.name}" + (f", {who}" if who else "") +
                 f": final product {a.total} of {a.max_total}")
        cam = case.camera
        out["png"] = str(assessment_picture(args.png, present, lab0, model.spacing_mm,
                                            model.grid.origin_mm, model.structures,
                                            a.items, (cam.eye_mm, cam.focal_mm, cam.up),
                                            title, size=size))
    if args.json:
        print_json(out)
        return 0
    print(f"{s.path}: case {model.name}" + (f", {s.header.get('participant')}"
                                            if s.header.get("participant") else ""))
    for ln in m.checklist(a):
        print(ln)
    if "png" in out:
        print(f"wrote {out['png']}")
    return 0


def checklist_of_grid(model, grid) -> dict:
    """The assessment of a run's final tissue (``grid``: the headless main
    job's state or the window's replica), JSON-ready
    (:meth:`metrics.assessment.Assessment.as_dict`) with ``checklist``, its
    lines; only ``checklist`` (one line saying why) when the model has no
    case to assess against."""
    from bonesim.cli.research import research_module

    m = research_module("metrics.assessment", "the final-product checklist")
    try:
        a = m.assess_grid(model, grid)
    except ValueError as exc:
        return {"checklist": [f"final product: not assessed ({exc})"]}
    return {**a.as_dict(), "checklist": m.checklist(a)}


def print_checklist(assessment, file=None) -> None:
    """Print an assessment's checklist lines (``bonesim run``'s last words)."""
    for ln in (assessment or {}).get("checklist", []):
        print(ln, file=file or sys.stdout)
