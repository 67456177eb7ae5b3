"""The ``bonesim tutor`` commands: keygen, serve, join, playback.

They wire the tutoring pieces of :mod:`bonesim.tutoring.tutor` (the streamer and its
server, the sources, the trainee's control law) to the app, the trainee's
process (:mod:`bonesim.tutoring.trainee`) and its window (:mod:`bonesim.render.trainee`).
"""
from __future__ import annotations

import json
import math
import time

import numpy as np

from bonesim.cli.output import print_json
from bonesim.errors import BonesimError
from bonesim.net import packets as net
from bonesim.net.tutor_protocol import GLOSSARY
from bonesim.tutoring.server import TutorServer
from bonesim.tutoring.servo import Trainee, warmup
from bonesim.tutoring.sources import NetworkSource, RecordingSource

__all__ = ["GLOSSARY", "cmd_keygen", "cmd_serve", "cmd_join", "cmd_playback",
           "trainee_device_for"]


def _print(obj, as_json: bool, lines) -> None:
    if as_json:
        print_json(obj)
    else:
        for line in lines:
            print(line)


def _has_display() -> bool:
    import os

    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def cmd_keygen(args) -> int:
    """``bonesim tutor keygen FILE``."""
    p = net.write_key(args.file, overwrite=args.force)
    print(f"wrote a new 32-byte key to {p} (owner-only); copy it to the other machine "
          "over a trusted channel and pass it with --key-file")
    return 0


def cmd_serve(args) -> int:
    """``bonesim tutor serve``: run the instructor's haptic loop and stream it."""
    import sys

    from bonesim.io.case import load_case
    from bonesim.io.trajectory import read_trajectory

    key = net.load_key(args.key_file)
    traj = read_trajectory(args.trajectory) if args.trajectory else None
    headless = args.headless
    if args.device is not None and traj is not None:
        raise BonesimError("--device and --trajectory both drive the instructor's tool; "
                           "choose one", field="--device")
    if not headless and not _has_display():
        print("bonesim: no display found; serving headless (use --headless to ask for it "
              "explicitly)", file=sys.stderr)
        headless = True
    if headless and traj is None and args.device is None:   # nothing drives the tool: the demo
        from bonesim.io.toolpath import demo_trajectory

        traj = demo_trajectory(load_case(args.case), args.burr)
        start = int(np.flatnonzero(traj.drill)[0])
        traj = traj.at_times(traj.t_s[start:])
    if headless:
        return _serve_headless(args, key, traj)
    from bonesim.apps.simulator import App

    app = App(args.case, args.burr, script=traj, offscreen=False, sound=not args.no_sound,
              record=args.record, device=args.device)
    try:
        app.start()
        server = TutorServer(app.loop, key, host=args.host, port=args.port).start()
        print(f"bonesim: tutoring on {args.host}:{server.port} (case {app.model.name})",
              file=sys.stderr)
        try:
            frames = None if args.duration is None else max(1, int(args.duration * 60))
            summary = app.run(frames=frames)
        finally:
            final = server.close()
    finally:
        app.close()
    out = {"case": summary["case"], "port": server.port, "server": final,
           "voxels_removed": summary["voxels_removed"],
           "device_record": app.device_record}
    _print(out, args.json, [f"served {final.get('sent', 0)} packets to "
                            f"{final.get('joins', 0)} trainee join(s); "
                            f"{summary['voxels_removed']} voxels removed",
                            *_glossary_lines(final, None)])
    return 0


def _serve_headless(args, key: bytes, traj) -> int:
    import sys

    from bonesim.io.loading import load_model
    from bonesim.io.loading import warmup as model_warmup
    from bonesim.runtime.haptic_loop import HapticLoop

    from bonesim.io.case import load_case
    from bonesim.tutoring.devices import instructor_backend

    record = None
    if args.device is not None:                   # the instructor's hand: a real backend
        backend, record = instructor_backend(args.device, load_case(args.case))
        spec = ("device", backend)
        what = f"instructor's {args.device}"
    else:
        spec = ("scripted", traj)
        what = "scripted instructor"
    model_warmup()
    model = load_model(args.case, args.burr, **({"device": spec[1].caps} if record else {}))
    duration = args.duration
    if duration is None:
        duration = math.inf if traj is None else float(traj.t_s[-1] - traj.t_s[0])
    loop = HapticLoop(model, device=spec, run_s=None if math.isinf(duration) else duration)
    recorder = None
    if args.record:
        from bonesim.runtime.record import Recorder
        from bonesim.session.header import make_header

        header = make_header(model, input_device=args.device or "scripted",
                             device_record=record)
        recorder = Recorder(loop, args.record, header)
    t0 = time.monotonic()
    try:
        if recorder is not None:
            recorder.start()
        loop.start()
        server = TutorServer(loop, key, host=args.host, port=args.port).start()
        print(f"bonesim: tutoring on {args.host}:{server.port} (case {model.name}, "
              f"{what}" + ("" if math.isinf(duration) else f" for {duration:.1f} s")
              + "; Ctrl+C ends)", file=sys.stderr)
        try:
            loop.wait(duration + 30.0 if math.isfinite(duration) else None)
        except KeyboardInterrupt:
            pass
        finally:
            loop.stop()
            final = server.close()
            if recorder is not None:
                recorder.close()
        rates = loop.rate_stats(5000)
        removed = int(loop.state.removed_by_label.sum())
        device_status = _loop_device_status(loop) if record else None
    finally:
        loop.close()
    out = {"case": model.name, "host": args.host, "port": server.port,
           "duration_s": round(time.monotonic() - t0, 3),
           "haptic_rate_hz": round(rates["rate_hz"], 1), "voxels_removed": removed,
           "server": final, "device_record": record}
    if device_status is not None:
        out["device"] = device_status
    if args.record:
        out["record"] = str(args.record)
    rx = final.get("received", {})
    _print(out, args.json, [
        f"served case {model.name} on {args.host}:{server.port} for {out['duration_s']} s: "
        f"{final.get('sent', 0)} packets, {final.get('events_sent', 0)} tissue events sent, "
        f"{final.get('go_backs', 0)} go-backs, {final.get('joins', 0)} join(s)",
        "dropped: " + (", ".join(f"{k} {v}" for k, v in rx.items()
                                  if k != "accepted" and v) or "none"),
        f"haptic loop {out['haptic_rate_hz']} Hz, {removed} voxels removed"
        + (f"; recorded {args.record}" if args.record else ""),
        *_glossary_lines(final, None)])
    return 0


def _loop_device_status(loop) -> dict:
    """The instructor device's safety state as the haptic loop published it."""
    from bonesim.devices.safety import STATES

    st = loop.status
    out = {}
    for k, name in (("device_state", "state"), ("device_unplugs", "unplugs"),
                    ("device_rejected", "rejected")):
        if k in st.dtype.names:
            v = st[k]
            out[name] = (STATES[int(v)] if name == "state" and 0 <= int(v) < len(STATES)
                         else v.tolist() if hasattr(v, "tolist") else v)
    return out


def _glossary_lines(server: dict | None, trainee: dict | None) -> list:
    """The glossary lines for the words a summary shows."""
    shown = []
    if trainee is not None:
        if trainee.get("packets", {}).get("stale"):
            shown.append("stale")
        if trainee.get("link_lost_events") or trainee.get("link_lost"):
            shown.append("link lost")
    if server is not None:
        if server.get("received", {}).get("stale"):
            shown.append("stale")
        if server.get("go_backs"):
            shown.append("go-back")
    return ["  " + GLOSSARY[w] for w in dict.fromkeys(shown)]


def _ideal_lines(s: dict) -> list:
    """The tracking error beside the ideal follower's
    (:func:`bonesim.tutoring.ideal.compare`), and what limits it."""
    v = s.get("tracking_vs_ideal")
    if not v or not v.get("value"):
        return []
    from bonesim.tutoring.ideal import HANDICAPS

    a, i, lt = v["tool"]["session"], v["tool"]["ideal"], v["law_target"]
    out = [f"tracking error (distance to the instructor's tool) median {a['p50']} mm, p95 "
           f"{a['p95']} mm; the ideal follower's {i['p50']} mm, {i['p95']} mm (in bone "
           "contact the law itself holds a passive follower |F_instructor| / K_p off the tool)",
           f"following the law: mean distance to its target {lt['session']['mean']} mm, the "
           f"ideal follower's {lt['ideal']['mean']} mm (same law, gain, force cap and "
           f"{v['seconds']} s scored; no link delay, no join ramp, no hand): ratio {v['value']}"]
    worst = v.get("limited_by")
    if worst:
        out.append(f"what limits it most: {HANDICAPS[worst]} (the ideal with that alone: "
                   f"{v['handicaps'][worst]} mm)")
    return out


def _trainee_lines(s: dict) -> list:
    lat = s.get("latency_ms", {})
    err = s.get("tracking_error_mm", {})
    pk = s.get("packets", {})
    dev = s.get("device")
    return [
        f"{s['ticks']} servo ticks; packets accepted {pk.get('accepted', 0)}, dropped: "
        + (", ".join(f"{k} {v}" for k, v in pk.items() if k != "accepted" and v) or "none"),
        f"latency p50 {lat.get('p50')} ms, p99 {lat.get('p99')} ms; tracking error p50 "
        f"{err.get('p50')} mm, p99 {err.get('p99')} mm",
        f"tissue events applied {s.get('events_applied', 0)}; link lost "
        f"{s['link_lost_events']} time(s); {s['hud']}",
        *_ideal_lines(s),
        *([f"trainee device {s['device_record']['backend']}: {dev['state']}, unplugged "
           f"{dev['unplugs']} time(s), samples rejected {dev['rejected']}"] if dev else []),
        *_glossary_lines(None, s)]


def _window_mode(args) -> bool:
    """Whether ``tutor join`` / ``tutor playback`` open the trainee's window."""
    import sys

    if args.headless:
        return False
    if args.offscreen or _has_display():
        return True
    print("bonesim: no display found; following headless (use --headless to ask for it "
          "explicitly, or --offscreen --screenshot FILE.png for a picture)", file=sys.stderr)
    return False


def _trainee_window(args, source: tuple) -> dict:
    """Run the trainee's servo in its process and its window here; returns
    the servo's statistics with the window's summary under ``"window"``."""
    import sys

    from bonesim.render.trainee import TraineeApp
    from bonesim.tutoring.trainee import TraineeProcess

    duration = math.inf if args.duration is None else args.duration
    with TraineeProcess(source, duration_s=duration, device=args.device) as proc:
        print(f"bonesim: following the {proc.what} (case {proc.model.name})", file=sys.stderr)
        with TraineeApp(proc, size=args.size, offscreen=args.offscreen) as app:
            shot = args.screenshot or ("bonesim-trainee.png" if args.offscreen else None)
            try:
                win = app.run(frames=args.frames, screenshot=shot)
            except KeyboardInterrupt:
                win = {}
        s = proc.stop()
    if not s:
        raise BonesimError("the trainee process ended without its statistics")
    s["window"] = win
    return s


def _write_record(args, s: dict, source: tuple, model=None) -> None:
    """``--record FILE.json``: the trainee's session record, a header as a
    recording's (:func:`bonesim.runtime.record.make_header`: case, model,
    ``device_record``) and the summary ``s``; ``s["record"]`` names it.
    Without ``model`` (the window's process had it) the header keeps the
    device record and the source only."""
    path = getattr(args, "record", None)
    if not path:
        return
    from pathlib import Path

    rec = s.get("device_record")
    if model is not None:
        from bonesim.session.header import make_header

        header = make_header(model, input_device=rec["backend"] if rec else "",
                             device_record=rec)
    else:
        header = {"device_record": rec}
    header["role"] = "trainee"
    header["source"] = list(source)
    try:
        Path(path).write_text(json.dumps({"header": header, "summary": s}, indent=2,
                                         default=str))
    except OSError as exc:
        raise BonesimError(f"cannot write the trainee's record: {exc.strerror or exc}",
                           path=path) from None
    s["record"] = str(path)


def _check_device(name) -> None:
    """Refuse an unknown or unsuitable trainee device before connecting (one
    line naming --device)."""
    if name is None:
        return
    from bonesim.devices.registry import AUXILIARY, BACKENDS, device_caps

    if name not in BACKENDS:
        known = ", ".join(n for n in BACKENDS if n not in AUXILIARY)
        raise BonesimError(f"unknown device {name!r}; known: {known}", field="--device")
    if BACKENDS[name][0] is None or name in AUXILIARY \
            or not math.isfinite(device_caps(name).max_force_n):
        raise BonesimError(f"the trainee device {name!r} renders no force; tutoring drives "
                           "the trainee's device (touch, simulated-hand)", field="--device")


def trainee_device_for(name, src, start_mm=None) -> tuple:
    """``(device, record)`` for the trainee (the bare simulated hand when no
    ``name`` is given; :func:`bonesim.tutoring.trainee.open_trainee_device`),
    its origin at ``start_mm`` [mm] (default the source's latest sample)."""
    from bonesim.tutoring.trainee import open_trainee_device

    return open_trainee_device(name, src, src.state.pos_mm if start_mm is None else start_mm)


def _window_lines(s: dict) -> list:
    w = s.get("window") or {}
    if not w:
        return []
    return [f"window: {w.get('frames', 0)} frames at {w.get('frame_hz', 0)} Hz, "
            f"{w.get('removed', 0)} removals drawn"
            + (f"; wrote {w['screenshot']}" if w.get("screenshot") else "")]


def cmd_join(args) -> int:
    """``bonesim tutor join HOST``: follow an instructor with the simulated hand."""
    import sys

    key = net.load_key(args.key_file)
    _check_device(args.device)
    if _window_mode(args):
        s = _trainee_window(args, ("network", args.host, args.port, key, args.case,
                                   args.timeout))
        _write_record(args, s, ("network", args.host, args.port))
        _print(s, args.json, _trainee_lines(s) + _window_lines(s))
        return 0
    warmup()
    src = NetworkSource(args.host, args.port, key, case=args.case)
    trainee = None
    try:
        src.connect(args.timeout)
        device, record = trainee_device_for(args.device, src)
        trainee = Trainee(src, device)
        print(f"bonesim: following the instructor at {args.host}:{args.port} (case "
              f"{src.info.get('case')})", file=sys.stderr)
        s = trainee.follow(math.inf if args.duration is None else args.duration)
        s["device_record"] = record
    finally:
        if trainee is not None:
            trainee.close()
            trainee.device.close()
        else:
            src.close()
    _write_record(args, s, ("network", args.host, args.port), src.model)
    _print(s, args.json, _trainee_lines(s))
    return 0


def cmd_playback(args) -> int:
    """``bonesim tutor playback FILE.h5``: drive the trainee's device from a recording."""
    from bonesim.session.reader import read_session

    recall = _recall(args.file, args.score) if args.score else None    # before: fail early
    _check_device(args.device)
    if _window_mode(args):                        # the servo's process reads the file
        s = _trainee_window(args, ("recording", str(args.file), args.speed, args.start))
        s["file"] = str(args.file)
        if recall is not None:
            s["recall"] = recall
        _write_record(args, s, ("recording", str(args.file)))
        _print(s, args.json, _playback_lines(s, args.file) + _window_lines(s)
               + _recall_lines(recall))
        return 0
    warmup()
    src = RecordingSource(read_session(args.file), speed=args.speed, start_s=args.start)
    try:
        tl = src.timeline
        device, record = trainee_device_for(
            args.device, src, tl.samples["pos_mm"][tl.sample_index(src.start_s)])
    except BaseException:
        src.close()
        raise
    trainee = Trainee(src, device)
    try:
        s = trainee.follow(math.inf if args.duration is None else args.duration)
        s["file"] = str(args.file)
        s["device_record"] = record
    finally:
        trainee.close()
        trainee.device.close()
    if recall is not None:
        s["recall"] = recall
    _write_record(args, s, ("recording", str(args.file)), src.model)
    _print(s, args.json, _playback_lines(s, args.file) + _recall_lines(recall))
    return 0


def _recall(expert, trainee) -> dict:
    """The trainee's run scored against the played-back run's force profile:
    force-trajectory alignment (:func:`metrics.alignment.align_sessions`,
    imported by name when asked: the simulator does not depend on the
    research metrics)."""
    import importlib

    from bonesim.errors import BonesimError

    try:
        align = importlib.import_module("metrics.alignment").align_sessions
    except ImportError as exc:                      # a simulator installed without them
        raise BonesimError(f"--score needs the research metrics ({exc})") from None
    try:
        out = align(str(expert), str(trainee)).summary()
    except ValueError as exc:
        raise BonesimError(f"--score: {exc}", path=trainee) from None
    out["trainee"] = str(trainee)
    return out


def _recall_lines(recall) -> list:
    if recall is None:
        return []
    return [f"{recall['trainee']} against this run's force profile: residual "
            f"{recall['rms_n']:.3f} N after alignment ({recall['unaligned_rms_n']:.3f} N "
            f"before; time warped by up to {recall['max_abs_offset_s']:.2f} s)"]


def _playback_lines(s: dict, path) -> list:
    return [f"played back {s['playback_s']} s of {s['duration_s']} s from {path}; tracking "
            f"error p50 {s.get('tracking_error_mm', {}).get('p50')} mm, force max "
            f"{s.get('force_n', {}).get('max')} N; {s['hud']}", *_ideal_lines(s)]
