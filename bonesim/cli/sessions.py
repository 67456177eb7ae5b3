"""The ``bonesim sessions`` and ``bonesim replay`` commands.

Every command reads session files through
:func:`bonesim.session.reader.read_session`, so a damaged file gives one line
saying what is wrong and the command works on its readable part.
"""
from __future__ import annotations

import sys
from pathlib import Path

from bonesim.cli.output import print_json, print_table
from bonesim.errors import BonesimError
from bonesim.io.anatomy import clinical_name
from bonesim.session.header import sessions_folder
from bonesim.session.reader import (damage_notice, list_sessions, read_session, repair_session,
                                    session_info)

__all__ = ["cmd_sessions_info", "cmd_sessions_list", "cmd_sessions_repair", "cmd_replay",
           "cmd_playback"]


def _say_damage(session) -> None:
    """One line on stderr when ``session`` is damaged."""
    line = damage_notice(session)
    if line:
        print(line, file=sys.stderr)


def cmd_sessions_info(args) -> int:
    """Print a session's summary; exit status 1 when the file is damaged
    (one line on stderr says what is wrong and what is used)."""
    session = read_session(args.file)
    info = session_info(session)
    status = 0 if session.damage is None else 1
    if getattr(args, "against_current", False):
        from bonesim.session.drift import against_current

        info["against_current"] = against_current(session)
    if args.json:
        print_json(info)
        _say_damage(session)
        return status
    for k, v in info.items():
        if v is None and k in ("damage", "repaired_from", "readable_rows"):
            continue
        if k == "against_current":
            _print_drift(v)
        elif k == "readable_rows":
            print("readable: " + ", ".join(f"{g} {r['kept']} of {r['declared']} rows"
                                           for g, r in v.items()))
        elif k == "injuries":
            print(f"injuries: {len(v)}")
            for i in v[:20]:
                print(f"  {i['t_s']:9.3f} s  {i['kind']:8s} {clinical_name(i['structure'])}")
        elif k == "removed_by_structure":
            print(f"{k}: " + (", ".join(f"{clinical_name(kk)} {vv}" for kk, vv in v.items())
                              or "none"))
        elif isinstance(v, dict):
            print(f"{k}: " + (", ".join(f"{kk} {vv}" for kk, vv in v.items()) or "none"))
        else:
            print(f"{k}: {v}")
    _say_damage(session)
    return status


def _print_drift(d: dict) -> None:
    """``--against-current`` as lines: one per recorded file that differs."""
    print(f"against today's files (bonesim {d['recorded_version']} recorded it, this is "
          f"{d['current_version']}): {d['differs']} of {len(d['items'])} differ"
          + ("; the file carries its model, so it plays back, replays and scores as "
             "recorded" if d["self_contained"] and d["differs"] else ""))
    for i in d["items"]:
        print(f"  {i['what']}: {i['status']}" + (f" ({i['detail']})" if i["detail"] else ""))


def cmd_sessions_list(args) -> int:
    if args.folder is None and not sessions_folder().is_dir():
        # before the first recording the default folder does not exist yet: that
        # is no error (a folder asked for by name still has to exist)
        if args.json:
            print_json([], "sessions")
        else:
            print(f"no sessions yet: bonesim run --record saves them in "
                  f"{sessions_folder()}")
        return 0
    rows = list_sessions(args.folder)
    if args.json:
        print_json(rows, "sessions")
    elif not rows:
        print(f"no sessions in {args.folder or sessions_folder()}")
    else:
        print_table(rows, ["file", "start_time", "participant", "group", "case", "duration_s",
                      "voxels_removed", "injuries", "complete", "damage", "error"])
    return 0


def cmd_replay(args) -> int:
    from bonesim.io.loading import warmup
    from bonesim.session.replay import replay, verify

    session = read_session(args.file)
    _say_damage(session)
    warmup(session.recorded_burrs()[0])
    if args.verify:
        report = verify(session)
        if args.json:
            print_json(report)
        elif not report["samples_checked"]:
            print(f"{report['file']}: nothing checked: 0 of {report['samples_declared']:,} "
                  "samples readable")
        else:
            print(f"{report['file']}: checked {report['seconds_checked']} s, "
                  f"{report['samples_checked']:,} of {report['samples_declared']:,} samples; "
                  f"tissue events {report['events_replayed']} replayed vs "
                  f"{report['events_recorded']} recorded: "
                  f"{'identical' if report['tissue_match'] else 'DIFFERENT'}; "
                  f"forces {'identical' if report['forces_match'] else 'DIFFERENT'}")
            if report["first_mismatch"]:
                print(f"first difference: {report['first_mismatch']}")
        if report["short"]:
            print(f"bonesim: {report['file']}: not verified in full: {report['short']}",
                  file=sys.stderr)
        return 0 if report["ok"] else 1
    out = replay(session)
    res = {"file": str(session.path), "samples": int(len(session.samples["t_s"])),
           "voxels_removed": int(len(out["removals"]["t_s"]))}
    if args.json:
        print_json(res)
    else:
        print(f"{res['file']}: replayed {res['samples']} samples, "
              f"{res['voxels_removed']} voxels removed")
    return 0


def cmd_sessions_repair(args) -> int:
    out = Path(args.out)
    if out.exists() and not args.force:
        raise BonesimError(f"{out}: exists; choose a new file or pass --force",
                           field="out")
    fixed = repair_session(args.file, out, overwrite=args.force)
    info = session_info(fixed)
    if args.json:
        print_json(info)
        return 0
    src = fixed.repaired or {}
    what = f"damaged: {src['damage']}" if src.get("damage") else "no damage found"
    print(f"{args.file}: {what}")
    print(f"wrote {out}: {info['duration_s']} s, {info['samples']} samples, "
          f"{info['voxels_removed']} removals, {len(info['injuries'])} injuries")
    return 0


def cmd_playback(args) -> int:
    import os

    from bonesim.session.playback import Player
    from bonesim.session.video import parse_size
    from bonesim.session.reader import read_session

    from bonesim.session.reader import damage_notice

    session = read_session(args.file)
    notices = [] if session.complete else [
        "recording incomplete: the writer did not close the file (shown up to its last "
        "flush)"]
    if session.damage:
        print(damage_notice(session), file=sys.stderr)
        notices = [f"damaged file: {session.damage}"]
    if args.speed is not None and not args.speed > 0:
        raise BonesimError(f"speed must be positive, got {args.speed:g}", field="--speed")
    speed = 1.0 if args.speed is None else args.speed
    if args.video is not None:
        from bonesim.render.playback import export_video

        size = parse_size(args.size or "1280x720")
        out = export_video(Player(session), args.video, fps=args.fps, size=size,
                           speed=speed, start=args.start, end=args.end,
                           progress=not args.no_progress, notices=notices)
        out["file"] = str(session.path)
        if args.json:
            print_json(out)
        else:
            print(f"wrote {out['video']}: {out['frames']} frames, {size[0]}x{size[1]} at "
                  f"{args.fps:g} fps ({out['start_s']:.2f}-{out['end_s']:.2f} s of the "
                  f"recording at {speed:g}x), {out['frames_per_s']} frames/s")
        return 0
    offscreen = args.offscreen
    if not offscreen and not os.environ.get("DISPLAY") and not os.environ.get(
            "WAYLAND_DISPLAY"):
        raise BonesimError("no display found for the playback window; export a video "
                           "instead (--video OUT.mp4), or render a frame with --offscreen "
                           "--screenshot FILE.png")
    from bonesim.render.playback import PlaybackApp

    size = parse_size(args.size or "1280x720", even=False)
    player = Player(session)
    start = 0.0 if args.start is None else args.start
    if not 0.0 <= start <= player.timeline.duration:
        raise BonesimError(f"start {start:g} s lies outside the recording (0 .. "
                           f"{player.timeline.duration:.3f} s)", field="--start")
    app = PlaybackApp(player, size=size, offscreen=offscreen, speed=speed, start=start,
                      play=not args.paused, notices=notices)
    try:
        app.start()
        frames = args.frames if args.frames is not None else (1 if offscreen else None)
        screenshot = args.screenshot or ("bonesim-playback.png" if offscreen else None)
        out = app.run(frames=frames, screenshot=screenshot)
    finally:
        app.close()
    out["file"] = str(session.path)
    if args.json:
        print_json(out)
    else:
        print(f"{out['file']}: {out['frames']} frames; stopped at {out['t_s']:.2f} of "
              f"{out['duration_s']:.2f} s")
        if "screenshot" in out:
            print(f"wrote {out['screenshot']}")
    return 0
