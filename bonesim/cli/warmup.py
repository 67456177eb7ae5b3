"""Compile the numba kernels ahead of time (``bonesim warmup``).

Kernels are compiled on first use and cached on disk next to their modules
(``@njit(cache=True)``). A cold first run of the simulator therefore spends
about a minute compiling in its processes (haptic loop, sound, nerve
monitor, window) at once. :func:`warmup_all` compiles them all ahead, in two
processes side by side on a machine with two cores or more (the parts in
:data:`SECOND` in a child process, ``python -m bonesim.cli.warmup PART...``;
compiling is one core's work per process); ``scripts/setup.sh`` runs it
after installing, so the first ``bonesim run`` (and the test suite, which
imports the same files: an editable install) starts warm.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

__all__ = ["SECOND", "warmup_all", "cmd_warmup"]

#: Parts a second process compiles while this one compiles the others (about
#: half the time each: on a fresh clone of a 2-core machine, 66 + 5 s there
#: against 79 s here; parts that share kernels stay in one process, and the
#: sound, vibration and tutoring kernels share none).
SECOND = ("surface", "surface consumer", "mesh buffers", "thickness", "nerve monitor",
          "label stacks", "colour neighbours", "vibration", "sound", "clicks", "tutoring")


def _monitor() -> None:
    """The nerve monitor's distance lookup, and the dense copy of a model's
    read-only labels that it and the window's structure meshes start from."""
    import numpy as np

    from bonesim.io.loading import warmup_model
    from bonesim.runtime.monitor import NerveField

    mask = np.zeros((6, 6, 6), bool)
    mask[3, 3, 1:5] = True
    NerveField(mask, 0.5, (0.0, 0.0, 0.0), 1.0).distance([[0.5, 0.5, 0.5], [9.0, 9.0, 9.0]])
    warmup_model().grid.to_dense()


def _visibility() -> None:
    """The recorder's writer judges each removal's visibility (its kernels)."""
    import numpy as np

    from bonesim.engine import events
    from bonesim.io.loading import warmup_model
    from bonesim.physics.visibility import VisibilityTracker

    m = warmup_model()
    vt = VisibilityTracker([m], (3.0, 3.0, 20.0))
    vt.add_samples({"t_s": np.array([0.0]), "pos_mm": np.array([[3.0, 3.0, 2.9]]),
                    "burr": np.zeros(1, np.int64), "epoch": np.zeros(1, np.int64)})
    ev = events.empty_events(1)
    ev["ijk"][0] = (6, 6, 5)
    vt.judge(ev)


def _loop() -> None:
    """The haptic loop's process on the default case for half a second: its
    kernels compile there for the types of a real run (its state lives in
    shared memory), which the tiny models above do not all reach."""
    import numpy as np

    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.io.loading import load_model
    from bonesim.io.trajectory import Trajectory

    model = load_model("phantom", "cutting-5mm")
    cam = model.case.camera
    view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
    view /= np.linalg.norm(view)
    t = np.linspace(0.0, 0.5, 51)
    pos = np.asarray(cam.focal_mm, float) + (8.0 - 16.0 * t)[:, None] * view * -1.0
    traj = Trajectory(t_s=t, pos_mm=pos, axis=np.tile(view, (len(t), 1)),
                      drill=np.ones(len(t), bool), speed_rpm=np.full(len(t), 60000.0))
    loop = HapticLoop(model, device=("scripted", traj), run_s=0.6)
    try:
        loop.start()
        loop.wait(60.0)
    finally:
        loop.close()


def _parts():
    from bonesim.sound import clicks
    from bonesim.physics.dust import grid as dust
    from bonesim.io import label_slices, loading, neighbours
    from bonesim.runtime import simulate
    from bonesim.sound import drill as sound
    from bonesim.engine import surface
    from bonesim.engine import thickness
    from bonesim.physics import sightline
    from bonesim.tutoring import servo as tutor_servo
    from bonesim.physics import vibration
    from bonesim.render import meshbuf

    return [("haptic step", loading.warmup), ("surface", surface.warmup),
            ("surface consumer", simulate.warmup), ("mesh buffers", meshbuf.warmup),
            ("dust", dust.warmup),
            ("vibration", vibration.warmup), ("sound", sound.warmup),
            ("thickness", thickness.warmup), ("clicks", clicks.warmup),
            ("nerve monitor", _monitor), ("recording", _visibility),
            ("tutoring", tutor_servo.warmup), ("label stacks", label_slices.warmup),
            ("colour neighbours", neighbours.warmup),
            ("sight line", sightline.warmup),
            ("haptic loop", _loop)]


def warmup_all(report=None, starting=None, jobs: int = 1) -> dict:
    """Compile (or load from the cache) every kernel the simulator's
    processes use at start-up.

    Parameters
    ----------
    report : callable, optional
        Called with ``(name, seconds)`` after each part, in the order they
        finish (from this thread only).
    starting : callable, optional
        Called with ``(index, count, name)`` before each part (index from 1;
        one process only: with two, parts run side by side).
    jobs : int
        Processes: 1 compiles every part here in turn; 2 (or more) compiles
        the parts of :data:`SECOND` in a child process meanwhile.

    Returns
    -------
    dict
        Seconds per part [s].

    Raises
    ------
    BonesimError
        If the child process failed (its last lines of output are named).
    """
    parts = _parts()
    second = [n for n, _ in parts if n in SECOND] if jobs > 1 else []
    if not second:
        out = {}
        for k, (name, fn) in enumerate(parts, 1):
            if starting is not None:
                starting(k, len(parts), name)
            t0 = time.perf_counter()
            fn()
            out[name] = round(time.perf_counter() - t0, 3)
            if report is not None:
                report(name, out[name])
        return out
    return _side_by_side([p for p in parts if p[0] not in second], second, report)


def _side_by_side(mine, second, report) -> dict:
    """Run the parts ``mine`` here while a child runs the parts named ``second``."""
    from bonesim.errors import BonesimError

    child = subprocess.Popen([sys.executable, "-m", "bonesim.cli.warmup", *second],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ))
    done: list[tuple[str, float]] = []             # the child's parts as they finish
    err: list[str] = []
    lock = threading.Lock()

    def read_out():
        for line in child.stdout:
            try:
                name, sec = json.loads(line)
            except ValueError:
                continue
            with lock:
                done.append((str(name), float(sec)))

    readers = [threading.Thread(target=read_out, daemon=True),
               threading.Thread(target=lambda: err.extend(child.stderr), daemon=True)]
    for th in readers:
        th.start()
    out, shown = {}, 0

    def show_child():
        nonlocal shown
        with lock:
            new, shown = done[shown:], len(done)
        for name, sec in new:
            out[name] = round(sec, 3)
            if report is not None:
                report(name, out[name])

    try:
        for name, fn in mine:
            t0 = time.perf_counter()
            fn()
            out[name] = round(time.perf_counter() - t0, 3)
            if report is not None:
                report(name, out[name])
            show_child()
        while child.poll() is None:
            show_child()
            time.sleep(0.05)
    except BaseException:
        child.kill()
        child.wait()
        raise
    for th in readers:
        th.join()
    show_child()
    if child.returncode != 0 or set(second) - set(out):
        tail = " | ".join(line.strip() for line in err[-3:] if line.strip())
        raise BonesimError(f"the warm-up's second process failed (exit {child.returncode})"
                           + (f": {tail}" if tail else ""))
    return out


def cmd_warmup(args) -> int:
    """``bonesim warmup``: compile every kernel, saying what it does and how far
    it has got (a line per part), or one JSON object with ``--json``."""
    t0 = time.perf_counter()
    report = starting = None
    jobs = args.jobs if args.jobs is not None else min(2, os.cpu_count() or 1)
    if jobs < 1:
        from bonesim.errors import BonesimError

        raise BonesimError(f"--jobs must be at least 1, got {jobs}", field="--jobs")
    if not args.json:
        n = len(_parts())
        side = f", in {min(jobs, 2)} processes side by side" if jobs > 1 else ""
        print("bonesim: compiling the numba kernels, once: they are cached on disk for "
              f"every later run and the tests (about a minute on a quiet 2-core machine{side})",
              flush=True)
        if jobs > 1:
            count = [0]

            def report(name, sec):
                count[0] += 1
                print(f"  [{count[0]:2d}/{n}] {name:18s} {sec:7.2f} s", flush=True)
        else:
            def starting(k, n, name):
                print(f"  [{k:2d}/{n}] {name:18s}", end="", flush=True)

            def report(name, sec):
                print(f" {sec:7.2f} s", flush=True)
    parts = warmup_all(report, starting, jobs=jobs)
    total = round(time.perf_counter() - t0, 2)
    if args.json:
        from bonesim.cli.output import print_json

        print_json({"seconds": parts, "total_s": total})
    else:
        print(f"compiled the kernels in {total} s (cached for the next runs)")
    return 0


def _child(names) -> None:
    """The second process: run the named parts, one JSON line ``[name, seconds]``
    each as it finishes."""
    want = set(names)
    for name, fn in _parts():
        if name in want:
            t0 = time.perf_counter()
            fn()
            # the pipe to the parent (not an output for users: bonesim.cli.output)
            sys.stdout.write(json.dumps([name, round(time.perf_counter() - t0, 3)]) + "\n")
            sys.stdout.flush()


if __name__ == "__main__":
    _child(sys.argv[1:])
