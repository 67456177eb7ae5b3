"""Benchmark: the haptic loop's period while a fragment moves.

The loop runs on the phantom with the mouse device; a block of lateral
mastoid (the render tests' piece, 8 x 10 x 10 mm) is split off. The loop's
periods are measured twice in the same run: first with the fragment still
(the tool away, the drill stopped: the rigid step has nothing to move), then
with the fragment grabbed and carried by the tool along a circle above the
bone (every period moves it: contact against the bone, a POSE event). The
figures are reported, never asserted.
"""
from __future__ import annotations

import math
import time

import numpy as np

__all__ = ["PIECE_LO", "PIECE_HI", "CIRCLE_MM", "bench_rigid_loop"]

#: The fragment: voxel box (inclusive) of lateral mastoid.
PIECE_LO, PIECE_HI = (78, 44, 40), (94, 63, 59)
#: Radius of the circle the tool carries it along [mm], and its period [s].
CIRCLE_MM, CIRCLE_S = 6.0, 1.5


def _p(values, q) -> float:
    return float(np.percentile(np.asarray(values, float), q))


def bench_rigid_loop(quick=False) -> dict:
    """``haptic_loop_period_fragment_p99_ms`` and, from the same run,
    ``haptic_loop_period_still_p99_ms``."""
    from bonesim.engine import events
    from bonesim.io.loading import load_model
    from bonesim.runtime.commands import SplitBox
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.rigid_commands import GrabBody

    seconds = 2.0 if quick else 5.0
    model = load_model("phantom", "cutting-5mm")
    g = model.grid
    centre = g.origin_mm + g.spacing_mm * (np.add(PIECE_LO, PIECE_HI) / 2.0)
    cam = model.case.camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    loop = HapticLoop(model, vibration=False)
    out = {}
    try:
        loop.start()
        loop.set_drill(False)
        away = centre - 30.0 * view
        loop.set_target(away, view)
        loop.send(SplitBox, lo=PIECE_LO, hi=PIECE_HI, body=0)
        end = time.monotonic() + 20.0
        while loop.state.n_bodies < 2 and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.5)
        # still: the fragment exists, nothing moves
        h0 = loop.steps_measured
        time.sleep(seconds)
        still = loop.recent_periods(loop.steps_measured - h0)[1:] * 1e3
        # the tool into the fragment's centre, grab, lift, carry along a circle
        loop.set_target(centre, view)
        time.sleep(0.5)
        loop.send(GrabBody, body=1)
        time.sleep(0.1)
        up = -view
        a = np.cross(up, [0.0, 0.0, 1.0])
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        lift = centre + 12.0 * up
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:
            f = (time.monotonic() - t0) / 0.5
            loop.set_target(centre + f * (lift - centre), view)
            time.sleep(0.005)
        ev0 = loop.state.tissue.count
        h0 = loop.steps_measured
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            ph = 2 * math.pi * (time.monotonic() - t0) / CIRCLE_S
            loop.set_target(lift + CIRCLE_MM * (math.cos(ph) * a + math.sin(ph) * b), view)
            time.sleep(0.005)
        moving = loop.recent_periods(loop.steps_measured - h0)[1:] * 1e3
        ev = loop.state.tissue.read(ev0)
        poses = int((ev["kind"] == events.POSE).sum())
        rejected = int(loop.status["commands_rejected"])
        realtime = bool(loop.status["realtime"])
    finally:
        loop.close()
    setup = ("haptic loop in its own process (mouse device, phantom, cutting-5mm); an "
             "8 x 10 x 10 mm fragment split off; 'still': tool away, nothing moves; "
             "'moving': grabbed and carried by the tool along a 6 mm circle above the bone")
    out["haptic_loop_period_fragment_p99_ms"] = {
        "value": round(_p(moving, 99), 3), "unit": "ms", "p50_ms": round(_p(moving, 50), 3),
        "max_ms": round(float(moving.max()), 3), "periods": int(len(moving)),
        "poses_published": poses, "poses_per_period": round(poses / max(len(moving), 1), 3),
        "still_p99_ms": round(_p(still, 99), 3), "commands_rejected": rejected,
        "realtime_priority": realtime, "setup": setup}
    out["haptic_loop_period_still_p99_ms"] = {
        "value": round(_p(still, 99), 3), "unit": "ms", "p50_ms": round(_p(still, 50), 3),
        "max_ms": round(float(still.max()), 3), "periods": int(len(still)),
        "realtime_priority": realtime, "setup": setup}
    return out
