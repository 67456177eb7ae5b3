"""The drilling commands: ``bonesim simulate``, ``trajectory``, ``demo`` and
``run`` (the interactive simulator, or without a display the headless main
job)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bonesim.cli.assess import checklist_of_grid, print_checklist
from bonesim.cli.devices import device_option
from bonesim.cli.output import print_json
from bonesim.cli.voxel import voxel_option
from bonesim.errors import EXIT_RECORDING_LOST, BonesimError
from bonesim.io.anatomy import clinical_name
from bonesim.io.burrs import DEFAULT_BURR

__all__ = ["DEFAULT_CASE", "cmd_trajectory", "cmd_simulate", "cmd_demo", "cmd_run",
           "drilling_parsers"]

#: The case the commands drill when none is named.
DEFAULT_CASE = "phantom"


def _checked(case, args):
    """The case (a name, path or Case), refused when its anatomy contradicts
    its declared side or orientation unless ``--accept-orientation``."""
    from bonesim.io.case import load_case

    case = case if hasattr(case, "require_orientation") else load_case(case)
    problem = case.require_orientation(getattr(args, "accept_orientation", False))
    if problem:
        print(f"bonesim: {case.manifest}: {problem}; drilled as declared "
              "(--accept-orientation)", file=sys.stderr)
    return case


def _plan(case, burr_name: str):
    """The demo mastoidectomy (cutting burr, then the plan's diamond burr)."""
    from bonesim.io.toolpath import plan_mastoidectomy

    return plan_mastoidectomy(case, burr_name)


def cmd_trajectory(args) -> int:
    from bonesim.io.case import load_case
    from bonesim.io.trajectory import write_trajectory

    case = _checked(load_case(args.case), args)
    planned = _plan(case, args.burr)
    traj = planned.trajectory
    write_trajectory(args.out, traj)
    burrs = ", ".join(f"{i} {b}" for i, b in enumerate(planned.burrs))
    extra = " ".join(f"--extra-burr {b}" for b in planned.burrs[1:])
    print(f"wrote {args.kind} trajectory for case '{case.name}' ({len(traj.t_s)} points, "
          f"{traj.t_s[-1]:.1f} s; burr column: {burrs}) to {args.out}; drill it with "
          f"bonesim simulate --burr {planned.burrs[0]} {extra} --trajectory {args.out}")
    return 0


def _who(args) -> dict:
    return {"participant": args.participant or "", "group": args.group or "",
            "notes": args.notes or ""}


def _run(case, burr, traj, args) -> dict:
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import load_model, warmup
    from bonesim.runtime.simulate import run_trajectory

    warmup()
    model = load_model(case, burr, oversample=args.oversample)
    extra = [load_burr(b) for b in (getattr(args, "extra_burr", None) or ())]
    used = int(traj.burr.max())
    if used > len(extra):
        raise BonesimError(f"the trajectory's burr column goes up to {used}, but the run has "
                           f"burrs 0..{len(extra)} (name burrs 1, 2, ... with --extra-burr)",
                           field="--extra-burr")
    record = getattr(args, "record", None)
    header = None
    if record is not None:
        from bonesim.session.header import make_header

        header = make_header(model, extra, input_device="scripted", **_who(args))
    return run_trajectory(model, traj, check=args.check, out_dir=args.out,
                          mesh_format=args.mesh_format, record=record, header=header,
                          burrs=extra)


def cmd_simulate(args) -> int:
    from bonesim.io.trajectory import read_trajectory

    traj = read_trajectory(args.trajectory, progress="auto")
    case = _checked(args.case, args)
    summary = _run(case, args.burr, traj, args)
    if args.json:
        print_json(summary)
    else:
        _print_summary(summary)
    if summary.get("record_error"):
        print(f"bonesim: {summary['record_error']}", file=sys.stderr)
    elif summary.get("record_compact_error"):          # complete, left uncompressed
        print(f"bonesim: note: {summary['record_compact_error']}", file=sys.stderr)
    return 0 if summary.get("record_ok", True) else EXIT_RECORDING_LOST


def _shown(names) -> str:
    """Structure names as a surgeon reads them (clinical names), comma-separated."""
    return ", ".join(clinical_name(n) for n in names)


def _print_summary(s: dict) -> None:
    from bonesim.runtime.simulate import approach_text

    print(f"case {s['case']}, burr {s['burr']}: {s['steps']} haptic steps "
          f"({s['duration_s']} s simulated) in {s['wall_s']} s")
    print(f"removed {s['voxels_removed']} voxels ({s['volume_removed_mm3']} mm^3): "
          + ", ".join(f"{clinical_name(k)} {v}" for k, v in s["removed_by_structure"].items()))
    print(f"injuries: {len(s['injuries'])}"
          + "".join(f"\n  {i['t_s']:8.3f} s  {i['kind']:8s} {clinical_name(i['structure'])} "
                    f"({i['voxels']} voxels)" for i in s["injuries"][:20]))
    if "closest_approach" in s:
        c = s["closest_approach"]
        grid = " x ".join(f"{v:g}" for v in c["native_spacing_mm"])
        print(f"closest approach of the drilling burr: "
              f"{approach_text(c['clearance_mm'], c['structure'])} at {c['t_s']:.2f} s "
              f"(exact on the {grid} mm source grid)")
    print(f"force: mean {s['force_n']['mean']} N, in contact "
          f"{s['force_n']['mean_in_contact']} N, max {s['force_n']['max']} N")
    print(f"haptic step: p50 {s['haptic_step_us']['p50']} us, "
          f"p99 {s['haptic_step_us']['p99']} us")
    if "vertices" in s:
        print(f"surface: {s['vertices']} vertices, {s['triangles']} triangles")
    if "surface_consistent" in s:
        print(f"surface consistent with a from-scratch tessellation: "
              f"{s['surface_consistent']}")
    if "mesh" in s:
        print(f"wrote {s['mesh']} and {s['summary']}")
    if "record" in s and s.get("record_ok", True):
        print(f"recorded the session to {s['record']}")


def cmd_demo(args) -> int:
    from bonesim.io.case import load_case
    from bonesim.io.trajectory import write_trajectory

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    case = _checked(load_case(args.case), args)
    planned = _plan(case, args.burr)
    traj = planned.trajectory
    tpath = out / "trajectory.csv"
    write_trajectory(tpath, traj)
    import numpy as np

    dt = np.diff(traj.t_s)
    drilling = float(dt[traj.drill[:-1].astype(bool)].sum())
    print(f"planned a demo mastoidectomy on case '{case.name}' with "
          f"{' then '.join(planned.burrs)}: {traj.t_s[-1] - traj.t_s[0]:.1f} s "
          f"({drilling:.1f} s with the drill on, the rest travel and rinses), written "
          f"to {tpath}")
    args.check = True
    args.extra_burr = list(planned.burrs[1:])
    summary = _run(case, args.burr, traj, args)
    _print_summary(summary)
    return 0 if summary.get("surface_consistent", True) else 1


def cmd_run(args) -> int:
    import os

    from bonesim.apps.simulator import App
    from bonesim.io.case import load_case
    from bonesim.io.trajectory import read_trajectory

    offscreen = args.offscreen
    script = read_trajectory(args.script, progress="auto") if args.script else None
    frames = args.frames
    screenshot = args.screenshot
    if not offscreen and not os.environ.get("DISPLAY") and not os.environ.get(
            "WAYLAND_DISPLAY"):
        what = ("rendering offscreen" if script is not None or frames is not None else
                "running the headless main job instead")
        print(f"bonesim: no display found; {what} (use --offscreen to ask for it "
              "explicitly)", file=sys.stderr)
        offscreen = True
    if args.monitor_port is not None and args.no_monitor:
        raise BonesimError("--monitor-port serves the nerve monitor; it cannot go with "
                           "--no-monitor", field="--monitor-port")
    args.case = _checked(args.case, args)
    if offscreen and script is None and frames is None:
        if args.force_limits:
            raise BonesimError("the headless main job drills the planned path and shows no "
                               "warnings; force limits are for the live window (or "
                               "offscreen with --script or --frames)", field="--force-limits")
        return _run_showcase(args)
    if args.video is not None:
        raise BonesimError("--video is the headless main job's time-lapse; the live "
                           "simulator records with --record (bonesim video makes a video "
                           "of a recording)", field="--video")
    if offscreen:
        if script is None and args.device == "mouse":   # a glimpse of the plan
            from bonesim.io.toolpath import demo_trajectory

            traj = demo_trajectory(load_case(args.case), args.burr)
            import numpy as np

            start = int(np.flatnonzero(traj.drill)[0])
            script = traj.at_times(traj.t_s[start:])
        frames = frames or 300
        screenshot = screenshot or "bonesim-run.png"
    record = None if args.no_record else args.record   # --no-record: the old opt-out
    if record == "":
        from bonesim.session.header import default_session_path

        record = default_session_path(load_case(args.case).name, args.participant or "")
    if record is not None:         # room to record? (a window's run has no set length: warned)
        from bonesim.session.disk_guard import warn_space
        warn_space(record)
    serve = None
    if args.monitor_port is not None:
        from bonesim.net.packets import load_key

        serve = {"key": load_key(args.key_file), "host": args.monitor_host,
                 "port": args.monitor_port}
    app = App(args.case, args.burr, script=script, offscreen=offscreen,
              size=tuple(args.size) if args.size else (1024, 768),
              sound=not args.no_sound, wav=args.wav,
              record=record, who=_who(args), monitor=not args.no_monitor,
              monitor_serve=serve, stereo=args.stereo,
              eye_separation_mm=args.eye_separation_mm, force_limits=args.force_limits,
              fragments=not getattr(args, "no_fragments", False),
              device=None if args.device == "mouse" else args.device,
              pedal=args.pedal)
    try:
        app.start()
        if serve is not None:
            print(f"bonesim: nerve monitor on {args.monitor_host}:{app.monitor.port} "
                  f"({_shown(app.monitor.names)})", file=sys.stderr, flush=True)
        summary = app.run(frames=frames, screenshot=screenshot)
        summary["assessment"] = checklist_of_grid(app.model, app.consumer.grid)
    finally:
        app.close()
    summary.update(app.record_summary())      # record_ok, the kept span (after closing)
    if args.json:
        print_json(summary)
    else:
        print(f"case {summary['case']}, burr {summary['burr']}: {summary['frames']} frames "
              f"at {summary['frame_hz']} Hz; haptic loop {summary['haptic_rate_hz']} Hz "
              f"(period p99 {summary['haptic_period_p99_ms']} ms)")
        print(f"removed {summary['voxels_removed']} voxels; injuries: "
              f"{_shown(summary['injuries']) or 'none'}")
        for note in summary["notices"]:
            print(f"note: {note}")
        if "screenshot" in summary:
            print(f"wrote {summary['screenshot']}")
        if "wav" in summary:
            print(f"wrote {summary['wav']}")
        if "record" in summary and summary.get("record_ok", True):
            print(f"recorded the session to {summary['record']}")
        print_checklist(summary.get("assessment"))
    return 0 if summary.get("record_ok", True) else EXIT_RECORDING_LOST


def _run_showcase(args) -> int:
    """Headless ``bonesim run``: the whole demo plan in simulated time, as a
    time-lapse video and a final picture (:mod:`bonesim.apps.showcase`)."""
    from bonesim.apps.showcase import run_showcase

    for flag, given in (("--record", args.record is not None), ("--wav", args.wav),
                        ("--monitor-port", args.monitor_port is not None),
                        ("--stereo", args.stereo), ("--device", args.device != "mouse")):
        if given:
            raise BonesimError(f"{flag} needs the live simulator: add --frames N (offscreen) "
                               "or run on a display; the headless main job only drills the "
                               "plan in simulated time", field=flag)
    from bonesim.io.case_report import LoadProgress
    from bonesim.apps.showcase import SIZE

    # outputs only when asked: the plain main job writes its time-lapse and its
    # picture; asked for a picture (--screenshot), it writes that alone
    video = args.video or (None if args.screenshot else "bonesim-run.mp4")
    video = None if video == "none" else video
    bar = LoadProgress()
    try:
        out = run_showcase(args.case, args.burr, video=video,
                           picture=args.screenshot or "bonesim-run.png",
                           size=tuple(args.size) if args.size else SIZE,
                           monitor=not args.no_monitor, seconds=args.seconds,
                           progress=bar, assess=checklist_of_grid)
    finally:
        bar.close()
    if args.json:
        print_json(out)
        return 0
    print(f"case {out['case']}, burr {out['burr']}: the demo mastoidectomy, "
          f"{out['simulated_s']:.0f} s of simulated surgery in {out['steps']} haptic steps "
          f"({out['wall_s']:.0f} s here)")
    from bonesim.runtime.simulate import approach_text

    print(f"removed {out['voxels_removed']} voxels ("
          + ", ".join(f"{clinical_name(k)} {v}" for k, v in out["removed_by_structure"].items())
          + f"); injuries: {_shown(out['injuries']) or 'none'}")
    if "min_clearance_mm" in out:
        print("closest approach: " + approach_text(out["min_clearance_mm"],
                                                   out["min_clearance_structure"]))
    print(f"wrote {out['picture']}" + (
        f" and {out['video']} ({out['frames']} frames: a time-lapse running "
        f"{out['speedup']:g} times faster than the simulated surgery)"
        if "video" in out else ""))
    print_checklist(out.get("assessment"))
    return 0


def drilling_parsers(sub) -> None:
    """Add the drilling commands to the ``bonesim`` subparsers ``sub``."""
    from bonesim.net.packets import DEFAULT_KEY_HELP as KEY_HELP
    from bonesim.net.packets import MONITOR_PORT

    def run_opts(s, need_traj):
        s.add_argument("--case", default=DEFAULT_CASE,
                       help=f"case name or case.toml path (default {DEFAULT_CASE})")
        s.add_argument("--burr", default=DEFAULT_BURR,
                       help=f"burr name or file (default {DEFAULT_BURR})")
        if need_traj:
            s.add_argument("--trajectory", required=True,
                           help="CSV: t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,"
                                "speed_rpm[,direction]")
        s.add_argument("--oversample", type=int, default=2,
                       help="burr samples per voxel edge (default 2)")
        s.add_argument("--mesh-format", choices=["ply", "vtp"], default="ply",
                       help="final surface mesh format (default ply)")
        accept_opt(s)
        voxel_option(s)

    def accept_opt(s):
        s.add_argument("--accept-orientation", action="store_true",
                       help="drill a case whose anatomy contradicts its declared side or "
                            "orientation (refused by default, naming the code that fits)")

    def who_opts(s):
        s.add_argument("--participant", help="participant id, stored in the recording")
        s.add_argument("--group", help="participant group (e.g. resident, expert)")
        s.add_argument("--notes", help="free notes stored in the recording")

    s = sub.add_parser("simulate", help="drill a scripted trajectory headless at 1 kHz")
    s.add_argument("--record", metavar="FILE.h5", help="record the session to this file")
    s.add_argument("--extra-burr", action="append", metavar="NAME",
                   help="burr 1, 2, ... (repeatable) that the trajectory's burr column "
                        "switches to; --burr is burr 0")
    who_opts(s)
    run_opts(s, True)
    s.add_argument("--out", help="folder for the final mesh and summary.json")
    s.add_argument("--check", action="store_true",
                   help="verify the incremental surface against a from-scratch one")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("trajectory", help="write a planned trajectory for a case")
    s.add_argument("--case", default=DEFAULT_CASE, help="case name or case.toml path")
    s.add_argument("--kind", default="demo-mastoidectomy", choices=["demo-mastoidectomy"])
    s.add_argument("--burr", default=DEFAULT_BURR, help="burr the path is planned for")
    s.add_argument("--out", required=True, help="output CSV")
    accept_opt(s)
    voxel_option(s)
    s.set_defaults(func=cmd_trajectory)

    s = sub.add_parser("demo", help="headless demo: plan and drill a mastoidectomy on "
                                    "the default case, write the mesh and a summary")
    run_opts(s, False)
    s.add_argument("--out", default="bonesim-demo", help="output folder")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("run", help="the interactive simulator (window, haptic loop, "
                                   "sound, dust); without a display the headless main "
                                   "job: the demo plan in simulated time, video + picture")
    s.add_argument("--case", default=DEFAULT_CASE,
                   help=f"case name or case.toml path (default {DEFAULT_CASE})")
    s.add_argument("--burr", default=DEFAULT_BURR, help=f"starting burr (default {DEFAULT_BURR})")
    accept_opt(s)
    s.add_argument("--offscreen", action="store_true",
                   help="render without a display (OSMesa/EGL); default when none exists. "
                        "Alone: the headless main job (the whole demo plan in simulated "
                        "time); with --frames or --script: the live simulator offscreen")
    s.add_argument("--script", metavar="TRAJECTORY",
                   help="drive the tool from a trajectory CSV instead of the mouse "
                        "(offscreen default: the demo mastoidectomy)")
    s.add_argument("--frames", type=int, help="stop after this many frames (offscreen "
                                              "with --script: default 300)")
    s.add_argument("--screenshot", metavar="FILE.png", help="save the last frame")
    s.add_argument("--wav", metavar="FILE.wav", help="record the drill sound")
    s.add_argument("--no-sound", action="store_true", help="no audio process")
    s.add_argument("--record", metavar="FILE.h5", nargs="?", const="",
                   help="record the session (nothing is recorded unless asked): to "
                        "FILE.h5, or with no FILE to a new file in $BONESIM_SESSIONS "
                        "or ~/.local/share/bonesim/sessions")
    s.add_argument("--no-record", action="store_true", help=argparse.SUPPRESS)
    who_opts(s)
    s.add_argument("--size", type=int, nargs=2, default=None, metavar=("W", "H"),
                   help="window size [px] (default 1024 768; headless video 1280 720)")
    s.add_argument("--video", metavar="FILE.mp4",
                   help="headless main job: the time-lapse video (default "
                        "bonesim-run.mp4 unless --screenshot is given; 'none' for no "
                        "video)")
    from bonesim.render.stereo import STEREO_MODES        # (no VTK in that module)

    s.add_argument("--seconds", type=float, metavar="S",
                   help="headless main job: drill only the plan's first S seconds")
    s.add_argument("--stereo", choices=sorted(STEREO_MODES),
                   help="stereo view (anaglyph needs red-cyan glasses; quad-buffer a "
                        "stereo display)")
    s.add_argument("--eye-separation-mm", type=float, metavar="MM",
                   help="stereo: distance between the eyes [mm] (default from "
                        "bonesim/data/render.toml)")
    s.add_argument("--no-monitor", action="store_true",
                   help="no nerve monitor (default: on when the case monitors a nerve)")
    s.add_argument("--monitor-port", type=int, metavar="PORT",
                   help=f"stream the nerve monitor to remote consoles ('bonesim monitor "
                        f"HOST') on this UDP port ({MONITOR_PORT} is the consoles' default; "
                        "0: any free port)")
    s.add_argument("--monitor-host", default="0.0.0.0",
                   help="address the monitor server listens on (default all)")
    s.add_argument("--key-file", metavar="FILE", help="with --monitor-port: " + KEY_HELP)
    s.add_argument("--force-limits", metavar="FILE.toml",
                   help="warn in the HUD when force or speed near a structure goes above "
                        "these per-distance limits ('bonesim metrics limits' learns them "
                        "from expert runs)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.add_argument("--no-fragments", action="store_true",
                   help="do not split off bone that drilling cuts free (default: split "
                        "it into its own body; specks become dust)")
    device_option(s)
    voxel_option(s)
    s.set_defaults(func=cmd_run)
