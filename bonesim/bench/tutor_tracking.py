"""Benchmarks of tutoring's tracking and of the headless main job.

``tutor_tracking_vs_ideal``
    A loopback tutoring session on the built-in demo motion (the demo plan
    of the phantom from its first drilling sample, scripted in the
    instructor's haptic loop; :class:`~bonesim.tutoring.server.TutorServer`
    on 127.0.0.1; a :class:`~bonesim.tutoring.servo.Trainee` on the
    simulated hand in this process): the session's mean distance to the
    law's target over the ideal follower's, both scored at the session's
    own scored servo ticks (:func:`bonesim.tutoring.ideal.compare`). 1 means
    the session follows as well as the law allows; the detail has the span
    scored, the distances to the tool, the ideal re-run with each of the
    session's handicaps alone and, above 1.5, what limits it.
``main_job_s``
    Wall time of the whole headless main job (``bonesim run --offscreen``
    without a display: the demo plan drilled in simulated time, its
    time-lapse video and picture) in a child process, in a temporary
    folder. Minutes: it runs only when named (``--only main_job_s``).
"""
from __future__ import annotations

import time

__all__ = ["bench_tutor_tracking", "bench_main_job"]

_KEY = bytes(range(32))


def bench_tutor_tracking(quick: bool = False) -> dict:
    import numpy as np

    from bonesim.devices.simulated_hand import SimulatedHandDevice
    from bonesim.io.loading import load_model, warmup
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.tutoring.server import TutorServer
    from bonesim.tutoring.servo import Trainee
    from bonesim.tutoring.sources import NetworkSource
    from bonesim.tutoring.servo import warmup as tutor_warmup

    seconds = 5.0 if quick else 20.0
    warmup()
    tutor_warmup()
    model = load_model("phantom", "cutting-5mm")
    traj = demo_trajectory(model.case, "cutting-5mm")
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:])
    # the loop runs a little longer than the trainee follows (it joins after it starts)
    loop = HapticLoop(model, device=("scripted", traj), run_s=seconds + 10.0)
    trainee = None
    try:
        loop.start()
        server = TutorServer(loop, _KEY, host="127.0.0.1", port=0).start()
        try:
            src = NetworkSource("127.0.0.1", server.port, _KEY, model=model)
            src.connect(60.0)
            trainee = Trainee(src, SimulatedHandDevice())
            trainee.run(seconds)
            s = trainee.stats()
        finally:
            if trainee is not None:
                trainee.close()
            final = server.close()
    finally:
        loop.close()
    v = s.get("tracking_vs_ideal") or {}
    from bonesim.tutoring.ideal import HANDICAPS

    ratio = v.get("value")
    worst = v.get("limited_by")
    limits = None
    if ratio is not None and ratio > 1.5 and worst:
        limits = (f"over 1.5: mostly {HANDICAPS[worst]} (the ideal with that alone: "
                  f"{v['handicaps'][worst]} mm, the ideal {v['law_target']['ideal']['mean']} "
                  f"mm, the session {v['law_target']['session']['mean']} mm)")
    return {"tutor_tracking_vs_ideal": {
        "value": ratio, "unit": "ratio",
        "measure": "mean distance to the law's target P_i + F_i/K_p [mm], session / ideal, "
                   "at the same instants (the session's scored servo ticks)",
        "law_target_mm": v.get("law_target"), "tool_mm": v.get("tool"),
        "span_s": v.get("span_s"), "seconds_scored": v.get("seconds"),
        "ideal_damping_ns_per_mm": v.get("damping_ns_per_mm"),
        "link_delay_ms": v.get("delay_ms"), "late_ticks": v.get("late_ticks"),
        "ideal_with_one_handicap_mm": v.get("handicaps"), "limited_by": worst,
        "limits": limits, "seconds": seconds,
        "packets": s.get("packets"), "latency_ms": s.get("latency_ms"),
        "go_backs": final.get("go_backs"),
        "setup": "phantom demo plan from its first drilling sample, scripted instructor "
                 "loop -> TutorServer -> 127.0.0.1 UDP -> trainee servo (1 kHz) on the "
                 "simulated hand; ideal follower: same law, gain and force cap on a point "
                 "mass ticking at 1 kHz (bonesim/data/tutoring.toml), no link delay, no join "
                 "ramp, no hand"}}


def bench_main_job(quick: bool = False) -> dict:
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    import bonesim

    root = str(Path(bonesim.__file__).resolve().parents[1])
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH")
                                else "")
    with tempfile.TemporaryDirectory(prefix="bonesim-main-job-") as d:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "bonesim", "run", "--offscreen"], cwd=d,
                           env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        outputs = sorted(os.listdir(d))
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise RuntimeError(f"the main job failed (exit {p.returncode}): {tail}")
    return {"main_job_s": {"value": round(wall, 2), "unit": "s", "outputs": outputs,
                           "command": "bonesim run --offscreen (no display)",
                           "quick_ignored": bool(quick)}}
