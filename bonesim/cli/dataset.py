"""The ``bonesim dataset`` and ``bonesim sessions export`` commands.

``bonesim dataset RUN.h5 --out frames.h5`` renders one recording
(:func:`bonesim.render.dataset.make_dataset`); given a folder or a glob of
recordings it renders each in a task of its own on the Dask cluster the
metrics use (:mod:`metrics.dataset_cluster`, named here by module path only:
the simulator never imports the metrics). ``bonesim sessions export``
writes the bone at a moment of a recording as a case
(:mod:`bonesim.session.bone_export`).
"""
from __future__ import annotations

import sys
from pathlib import Path

from bonesim.cli.output import print_json
from bonesim.errors import BonesimError

__all__ = ["dataset_parsers", "options_from_args", "cmd_dataset", "cmd_sessions_export"]

_STREAM_FLAGS = ("rgb", "depth", "seg", "normals", "points")


def dataset_parsers(sub, _lazy, sessions_sub) -> None:
    """Add ``bonesim dataset`` to the subcommands ``sub`` and ``export`` to
    ``bonesim sessions``' ``sessions_sub``."""
    from bonesim.session.dataset_spec import (CAMERA_MODES, DEFAULT_FPS, DEFAULT_SIZE,
                                              SUCTION_MODES)
    from bonesim.session.bone_export import EXPORT_JSON

    s = sub.add_parser(
        "dataset", help="render a recorded run (or many) as a vision dataset: RGB, "
                        "stereo, depth, segmentation, normals, point clouds and cameras",
        description="Replay a recording and render each frame offscreen: RGB (without "
                    "the HUD unless --hud), metric depth along the optical axis [mm], the "
                    "segmentation of the first surface hit (the case's structures, burr, "
                    "shaft, suction tool, dust, water, plates; instance ids for fragments "
                    "and plates), per-frame OpenCV intrinsics and extrinsics, tool pose, "
                    "burr, drill state, removed voxels and time. Without stream flags it "
                    "writes --rgb --depth --seg. The output is one HDF5 file (OUT ending "
                    "in .h5) or a folder of PNG/TIFF images with index.json; the layout is "
                    "docs/dataset_format.md. The same command gives the same bytes. Given "
                    "a folder or glob of recordings it renders each on a Dask cluster "
                    "(one task per run) into the folder OUT.")
    s.add_argument("runs", metavar="RUN.h5|DIR|GLOB",
                   help="a session file, or a folder / glob pattern of session files")
    s.add_argument("--out", required=True, metavar="OUT",
                   help="frames.h5 (HDF5), or a folder (images + index.json); for many "
                        "runs a folder that receives one dataset per run")
    for f, what in (("rgb", "the picture"), ("depth", "metric depth [mm], float32"),
                    ("seg", "class and instance ids per pixel"),
                    ("normals", "surface normals (camera frame), from the depth"),
                    ("points", "point clouds in the camera and case frames")):
        s.add_argument(f"--{f}", action="store_true", help=f"write {what}")
    s.add_argument("--stereo", type=float, metavar="BASELINE_MM",
                   help="a parallel stereo pair this far apart [mm] (left and right)")
    s.add_argument("--camera", choices=CAMERA_MODES, default="recorded",
                   help="recorded (the recorded camera, else the case camera), fixed (the "
                        "case camera) or orbit (circling it); default recorded")
    s.add_argument("--size", metavar="WxH", default=f"{DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}",
                   help=f"frame size in pixels (default {DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]})")
    s.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help=f"frames per second of recording (default {DEFAULT_FPS:g})")
    s.add_argument("--start", type=float, metavar="S", help="from S seconds into the run")
    s.add_argument("--end", type=float, metavar="S", help="up to S seconds into the run")
    s.add_argument("--hud", action="store_true",
                   help="draw the window's HUD (and the hidden burr) over the RGB picture")
    s.add_argument("--suction", choices=SUCTION_MODES, default="follow",
                   help="the recording holds no suction-tip pose: follow draws the "
                        "suction-irrigator trailing the burr as the headless run does; "
                        "off draws none (default follow)")
    s.add_argument("--zoom", type=float, default=1.0,
                   help="move the camera this many times closer to its focal point")
    s.add_argument("--preview", metavar="FILE.png",
                   help="one run: also write the middle frame's RGB, depth and "
                        "segmentation side by side")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="many runs: a running Dask scheduler (default a local cluster)")
    s.add_argument("--workers", type=int, default=2, metavar="N",
                   help="many runs: worker processes of the local cluster (default 2)")
    s.add_argument("--layout", choices=("h5", "folder"), default="h5",
                   help="many runs: one .h5 file per run (default) or a folder per run")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=_lazy("bonesim.cli.dataset", "cmd_dataset"))

    e = sessions_sub.add_parser(
        "export", help="write the bone at a moment of a recording as a case (e.g. a "
                       "3D Slicer .seg.nrrd) to open in Slicer or drill on",
        description="Replay the recorded tissue events up to --at and write the remaining "
                    "voxels with their structures as a case in the patient frame, on the "
                    "recording's grid, with a case.toml (structures, colours, the camera "
                    f"of that moment) and {EXPORT_JSON} (where it came from). 'bonesim run "
                    "--case OUT/' goes on drilling it.")
    e.add_argument("file", help="session file (.h5)")
    e.add_argument("out", metavar="OUT/", help="folder to write the case into")
    e.add_argument("--at", type=float, metavar="S",
                   help="playback time [s] (default: the recording's last moment)")
    e.add_argument("--format", default="seg-nrrd",
                   choices=("seg-nrrd", "nrrd", "nifti", "label-stack", "dicom"),
                   help="seg-nrrd (default), nrrd, nifti, label-stack or dicom")
    e.add_argument("--orientation", metavar="CODE",
                   help="label-stack: axis code of the slices (default LPS)")
    e.add_argument("--force", action="store_true", help="overwrite a case.toml in OUT/")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=_lazy("bonesim.cli.dataset", "cmd_sessions_export"))


def options_from_args(args):
    """:class:`~bonesim.session.dataset_spec.DatasetOptions` of the parsed arguments."""
    from bonesim.session.dataset_spec import DatasetOptions
    from bonesim.session.video import parse_size

    flags = {f: bool(getattr(args, f, False)) for f in _STREAM_FLAGS}
    if not any(flags.values()):
        flags.update(rgb=True, depth=True, seg=True)
    return DatasetOptions(**flags, stereo_mm=args.stereo, camera=args.camera,
                          size=parse_size(args.size, even=False), fps=float(args.fps),
                          start=args.start, end=args.end, hud=bool(args.hud),
                          suction=args.suction, zoom=float(args.zoom))


def _one_run(path: str) -> bool:
    p = Path(path)
    return p.is_file() or (not p.exists() and not any(c in path for c in "*?[")
                           and p.suffix.lower() in (".h5", ".hdf5"))


def cmd_dataset(args) -> int:
    from bonesim.progress import ProgressBar

    opts = options_from_args(args)
    if not _one_run(args.runs):
        from bonesim.cli.research import research_module

        mod = research_module("metrics.dataset_cluster", "rendering many runs (Dask)")
        return mod.cmd_dataset_many(args, opts)
    if not Path(args.runs).is_file():
        raise BonesimError("no such session file", args.runs)
    from bonesim.io.loading import warmup
    from bonesim.render.dataset import make_dataset

    warmup()
    bars = []

    def progress(done, total):
        if not bars:                        # the first frame is rendered: show the bar
            bars.append(ProgressBar(total, "dataset"))
        bars[0].update(done)

    try:
        res = make_dataset(args.runs, args.out, opts,
                           progress=None if args.no_progress else progress)
    finally:
        for bar in bars:
            bar.close()
    if args.preview:
        from bonesim.session.dataset_io import open_dataset
        from bonesim.session.dataset_preview import write_preview

        with open_dataset(args.out) as d:
            i = len(d) // 2
            write_preview(args.preview, d.frame(i), d.attrs["classes"],
                          f"{Path(args.runs).name}  frame {i}  t = "
                          f"{d.frames['t_s'][i]:.2f} s")
        res["preview"] = str(args.preview)
    if args.json:
        print_json(res)
    else:
        for line in res["notes"]:
            print(line, file=sys.stderr)
        print(f"wrote {res['out']}: {res['frames']} frames of {res['size'][0]}x"
              f"{res['size'][1]} ({', '.join(res['eyes'])}) in {res['wall_s']:.1f} s "
              f"({res['frames_per_s']:.2f} frames/s)")
        if args.preview:
            print(f"wrote {args.preview}")
    return 0


def cmd_sessions_export(args) -> int:
    from bonesim.session.bone_export import export_bone
    from bonesim.session.reader import damage_notice, read_session

    session = read_session(args.file)
    line = damage_notice(session)
    if line:
        print(line, file=sys.stderr)
    res = export_bone(session, args.at, args.format, args.out, overwrite=args.force,
                      orientation=args.orientation)
    if args.json:
        print_json(res)
    else:
        print(f"{args.file}: the bone at {res['at_s']:.3f} s, {res['remaining_voxels']:,} "
              f"voxels ({res['removed_voxels']:,} removed) -> {res['case']}")
        if res["moved_bodies"]:
            print(f"moved fragments placed where they lay: bodies {res['moved_bodies']} "
                  f"({res['overlapping']} voxels overlapping left out)")
    return 0
