"""The case and burr commands: ``bonesim cases``, ``case-info``, ``case-export``
and ``burrs``."""
from __future__ import annotations

from pathlib import Path

from bonesim.cli.output import print_json, print_table
from bonesim.cli.voxel import voxel_option

__all__ = ["cmd_cases", "cmd_case_info", "cmd_case_export", "cmd_burrs", "case_parsers"]


def cmd_cases(args) -> int:
    from bonesim.io.case import list_cases

    rows = [{"name": c.name, "side": c.side, "format": c.volume.format,
             "manifest": str(c.manifest), "description": c.description}
            for c in list_cases()]
    if args.json:
        print_json(rows, "cases")
    else:
        print_table(rows, ["name", "side", "format", "description"])
    return 0


def cmd_case_info(args) -> int:
    from bonesim.io.case import case_info, load_case
    from bonesim.io.case_report import LoadProgress, print_case_info

    case = load_case(args.case)
    bar = LoadProgress()
    try:
        info = case_info(case, progress=bar)
    finally:
        bar.close()
    if args.png:
        from bonesim.render.landmarks_view import landmarks_picture

        info["png"] = str(landmarks_picture(case, args.png))
    if args.json:
        print_json(info)
    else:
        print_case_info(info)
        if args.png:
            print(f"wrote the landmarks picture {info['png']}")
    return 0


def cmd_case_export(args) -> int:
    from bonesim.io.case import export_case, load_case
    from bonesim.io.case_report import LoadProgress

    bar = LoadProgress()
    case = load_case(args.case)
    try:
        manifest = export_case(case, args.format, Path(args.dir),
                               orientation=args.orientation, progress=bar)
    finally:
        bar.close()
    what = args.format + (f" ({args.orientation})" if args.orientation else "")
    name = args.case if isinstance(args.case, str) else case.name
    print(f"wrote {what} export of case '{name}' to {args.dir} "
          f"(manifest {manifest})")
    return 0


# ------------------------------------------------------------------ burrs
def cmd_burrs(args) -> int:
    from bonesim.io.burrs import burr_table, list_burrs

    rows = burr_table(list_burrs())
    if args.json:
        print_json(rows, "burrs")
    else:
        cols = [c for c in ("name", "kind", "diameter_mm", "max_force_n",
                            "default_speed_rpm") if c in rows[0]]
        print_table(rows, cols)
    return 0


# ------------------------------------------------------ trajectories / runs


def case_parsers(sub) -> None:
    """Add the case and burr commands to the ``bonesim`` subparsers ``sub``."""
    s = sub.add_parser("cases", help="list the bundled cases")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_cases)

    s = sub.add_parser("case-info", help="frame, orientation, grid, camera, colours, "
                                         "monitored structures and voxels per structure; "
                                         "warns where the layout contradicts the side")
    s.add_argument("case", help="bundled case name or path of a case.toml")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.add_argument("--png", metavar="FILE.png",
                   help="draw the landmarks from the surgeon's view into this picture")
    voxel_option(s)
    s.set_defaults(func=cmd_case_info)

    s = sub.add_parser("case-export", help="write a case's volume as DICOM/NRRD/NIfTI/"
                                           "label stack/Slicer segmentation with a "
                                           "case.toml")
    s.add_argument("case", help="bundled case name or path of a case.toml")
    s.add_argument("--format", required=True,
                   choices=["dicom", "nrrd", "nifti", "label-stack", "seg-nrrd"])
    s.add_argument("--orientation", metavar="CODE",
                   help="label stacks: axis code of the written slices (columns, rows, "
                        "slices, e.g. PLS; default LPS)")
    s.add_argument("dir", help="output folder")
    voxel_option(s)
    s.set_defaults(func=cmd_case_export)

    s = sub.add_parser("burrs", help="list the burrs")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_burrs)
