"""The haptic loop process: it steps, publishes, resets, switches burrs and
never needs the consumer; the consumer's surface stays exact meanwhile."""
from __future__ import annotations

import time

import numpy as np
import pytest

from bonesim.io.burrs import load_burr
from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.io.loading import load_model
from bonesim.engine.replica import TissueReplica
from bonesim.engine.surface import Surface
from tests.bonesim.fakes import wait_for

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


def test_scripted_loop_publishes_and_consumer_stays_exact(model):
    traj = demo_trajectory(load_case("phantom"), "cutting-5mm")
    # skip the approach: start where the path first drills bone
    start = np.flatnonzero(traj.drill)[0]
    traj = traj.at_times(traj.t_s[start:start + 400])
    with HapticLoop(model, device=("scripted", traj)) as loop:
        consumer = TissueReplica(model, loop.state, surface=True)
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            consumer.drain()                   # the loop never waits for this
            time.sleep(0.02)
        loop.stop()
        consumer.drain()
        stats = loop.rate_stats()
        assert loop.status["steps"] > 500 and stats["n"] > 100 and stats["rate_hz"] > 0
        assert loop.state.n_removed > 0
        # the replica saw every published change, and the surface matches it
        np.testing.assert_array_equal(consumer.grid.density, loop.state.grid.density)
        fresh = Surface.of_model(model, consumer.grid)
        assert not fresh.canonical().differences(consumer.surface.canonical())


def test_mouse_device_drills_reset_restores_and_burr_switches(model):
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    with HapticLoop(model, burrs=[load_burr("diamond-3mm")]) as loop:
        # the cortex is near x = 20 on the focal line; ask for 3 mm into it
        loop.set_target(np.array([23.0, 3.0, -2.0]) + 3.0 * view, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_for(lambda: loop.state.n_removed > 20), "mouse drilling removed nothing"
        loop.set_drill(False)
        loop.set_burr(1)
        assert wait_for(lambda: loop.status["burr"] == 1)
        n_before = loop.state.tissue.count
        epoch = loop.reset()
        assert wait_for(lambda: loop.status["epoch"] == epoch)
        # the loop announces the epoch before it steps in it: every sample
        # published from here on belongs to the new epoch
        first_new = loop.samples.count
        assert wait_for(lambda: loop.state.removed_by_label.sum() == 0)
        np.testing.assert_array_equal(loop.state.grid.density, model.grid.density)
        # the event counters keep running, so other processes miss nothing
        assert loop.state.tissue.count > n_before        # + the reset event
        assert wait_for(lambda: loop.samples.count >= first_new + 10)
        smp = loop.samples.read(first_new, first_new + 10)
        assert (smp["epoch"] == epoch).all() and (smp["burr"] == 1).all()
        with pytest.raises(IndexError):
            loop.set_burr(5)


def test_loop_stops_by_itself_after_run_s(model):
    loop = HapticLoop(model, device=("null", (0.0, 0.0, 60.0), (0.0, 0.0, -1.0)), run_s=0.5)
    try:
        loop.start()
        assert loop.wait(20.0)
        assert not loop.running and loop.status["steps"] > 100
    finally:
        loop.close()
