"""Compile the numba kernels ahead of time (``bonesim warmup``).

Kernels are compiled on first use and cached on disk next to their modules
(``@njit(cache=True)``). A cold first run of the simulator therefore spends
about a minute compiling in its processes (haptic loop, sound, nerve
monitor, window) at once. :func:`warmup_all` compiles them all in one
process instead; ``scripts/setup.sh`` runs it after installing, so the first
``bonesim run`` (and the test suite) starts warm.
"""
from __future__ import annotations

import time

__all__ = ["warmup_all", "cmd_warmup"]


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
            ("haptic loop", _loop)]


def warmup_all(report=None, starting=None) -> dict:
    """Compile (or load from the cache) every kernel the simulator's
    processes use at start-up.

    Parameters
    ----------
    report : callable, optional
        Called with ``(name, seconds)`` after each part.
    starting : callable, optional
        Called with ``(index, count, name)`` before each part (index from 1).

    Returns
    -------
    dict
        Seconds per part [s].
    """
    out = {}
    parts = _parts()
    for k, (name, fn) in enumerate(parts, 1):
        if starting is not None:
            starting(k, len(parts), name)
        t0 = time.perf_counter()
        fn()
        out[name] = round(time.perf_counter() - t0, 3)
        if report is not None:
            report(name, out[name])
    return out


def cmd_warmup(args) -> int:
    """``bonesim warmup``: compile every kernel, saying what it does and how far
    it has got (a line per part), or one JSON object with ``--json``."""
    t0 = time.perf_counter()
    report = starting = None
    if not args.json:
        print("bonesim: compiling the numba kernels, once: they are cached on disk for "
              "every later run and the tests (about 2 minutes on a quiet 2-core machine)",
              flush=True)

        def starting(k, n, name):
            print(f"  [{k:2d}/{n}] {name:18s}", end="", flush=True)

        def report(name, sec):
            print(f" {sec:7.2f} s", flush=True)
    parts = warmup_all(report, starting)
    total = round(time.perf_counter() - t0, 2)
    if args.json:
        from bonesim.cli.output import print_json

        print_json({"seconds": parts, "total_s": total})
    else:
        print(f"compiled the kernels in {total} s (cached for the next runs)")
    return 0
