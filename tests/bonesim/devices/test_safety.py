"""The safety and fault layer: bad samples, force and stiffness limits, the
safe start, unplugging and plugging back in (in process, and in the haptic
loop's process with the mouse taking over)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bonesim.devices.interface import DeviceCaps, DeviceDisconnected, DeviceReading
from bonesim.devices.null import NullDevice
from bonesim.devices.safety import (
    ACTIVE,
    RAMPING,
    UNPLUGGED,
    WAITING,
    SafeDevice,
    SafetyLimits,
)
from bonesim.errors import BonesimError

CAPS = DeviceCaps("test-arm", 3.0, (100.0, 80.0, 60.0), 0.5)
DT = 1e-3
#: The servo time the fakes see (a device's open takes no time argument).
CLOCK = [0.0]


class FlakyDevice:
    """A device whose pose comes from a function of time and which is
    unplugged over given time spans (reads, writes and opens then fail)."""

    caps = CAPS

    def __init__(self, pose=lambda t: (0.0, 0.0, 0.0), unplugged=()):
        self.pose = pose
        self.unplugged = list(unplugged)
        self.forces = []
        self.t = 0.0
        self.opens = 0

    def _gone(self, t):
        return any(a <= t < b for a, b in self.unplugged)

    def open(self):
        self.t = CLOCK[0]
        if self._gone(self.t):
            raise BonesimError("test-arm: not found")
        self.opens += 1

    def read(self, t_s):
        self.t = t_s
        if self._gone(t_s):
            raise DeviceDisconnected("test-arm: gone")
        return DeviceReading(np.array(self.pose(t_s), float), np.array([0.0, 0.0, -1.0]))

    def write_force(self, f):
        if self._gone(self.t):
            raise DeviceDisconnected("test-arm: gone")
        self.forces.append((self.t, np.array(f, float)))

    def close(self):
        pass


class ListDevice:
    """Plays a list of readings, one per read."""

    caps = CAPS

    def __init__(self, readings):
        self.readings = list(readings)
        self.i = 0

    def open(self):
        pass

    def read(self, t_s):
        r = self.readings[min(self.i, len(self.readings) - 1)]
        self.i += 1
        return r

    def write_force(self, f):
        pass

    def close(self):
        pass


def _r(pos, axis=(0.0, 0.0, -1.0), t=None):
    return DeviceReading(np.array(pos, float), np.array(axis, float), t_s=t)


def _run(safe, n, force=lambda t: np.zeros(3), t0=0.0):
    """Read and write ``n`` servo ticks; returns times, readings and sent forces."""
    ts, rs, fs = [], [], []
    for k in range(n):
        t = t0 + k * DT
        CLOCK[0] = t
        rs.append(safe.read(t))
        safe.write_force(force(t))
        ts.append(t)
        fs.append(safe.sent_n.copy())
    return np.array(ts), rs, np.array(fs)


def test_nan_garbage_jump_and_stale_samples_are_rejected_and_the_pose_holds():
    good = _r((1.0, 2.0, 3.0), t=0.0)
    readings = [good,
                _r((math.nan, 2.0, 3.0), t=0.001),          # NaN
                _r((1.0, math.inf, 3.0), t=0.002),          # infinite
                _r((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), t=0.003),   # no axis
                _r((1.0, 2.0, 3.0), (math.nan, 0.0, 1.0), t=0.004),
                _r((1.0, 2.0, 3.0 + 61.0), t=0.005),        # beyond the 60 mm z range
                _r((1.0 - 101.0, 2.0, 3.0), t=0.006),       # beyond the 100 mm x range
                _r((1.0, 2.0, 3.0), t=0.007 - 0.2),         # measured 200 ms ago
                _r((1.5, 2.0, 3.0), t=0.008),
                _r((1.6, 2.0, 3.0), t=0.0075),              # timestamp going backwards
                _r((1.7, 2.0, 3.0), t=0.010)]
    safe = SafeDevice(ListDevice(readings))
    safe.open()
    _, rs, _ = _run(safe, len(readings))
    assert safe.rejected == {"nan": 4, "jump": 2, "stale": 2}
    assert safe.n_rejected == 8
    for k in range(1, 8):                                   # the previous pose held
        np.testing.assert_array_equal(rs[k].pos_mm, (1.0, 2.0, 3.0))
    np.testing.assert_array_equal(rs[8].pos_mm, (1.5, 2.0, 3.0))
    np.testing.assert_array_equal(rs[9].pos_mm, (1.5, 2.0, 3.0))
    np.testing.assert_array_equal(rs[10].pos_mm, (1.7, 2.0, 3.0))


def test_a_lasting_jump_is_taken_after_the_resync_count_and_restarts_the_safe_start():
    limits = SafetyLimits(resync_samples=5, still_for_s=0.002, ramp_s=0.002)
    readings = [_r((0.0, 0.0, 0.0))] * 20 + [_r((0.0, 0.0, 500.0))] * 20
    safe = SafeDevice(ListDevice(readings), limits=limits)
    safe.open()
    _, rs, _ = _run(safe, 20)
    assert safe.state == ACTIVE
    _, rs, _ = _run(safe, 20, t0=0.02)
    assert safe.rejected["jump"] == 4                        # the fifth is taken
    assert rs[3].pos_mm[2] == 0.0 and rs[4].pos_mm[2] == 500.0
    assert any(w == "resync" for _, w in safe.take_events())


def test_force_never_exceeds_the_maximum_and_nan_forces_become_zero():
    limits = SafetyLimits(still_for_s=0.001, ramp_s=0.001, slew_n_per_s=1e9)
    safe = SafeDevice(FlakyDevice(), limits=limits)
    safe.open()
    _run(safe, 5)
    assert safe.state == ACTIVE
    _, _, fs = _run(safe, 50, force=lambda t: np.array([30.0, -40.0, 0.0]), t0=0.005)
    mags = np.linalg.norm(fs, axis=1)
    assert mags.max() <= CAPS.max_force_n * (1 + 1e-12)
    np.testing.assert_allclose(fs[-1], [1.8, -2.4, 0.0])       # the direction is kept
    _, _, fs = _run(safe, 3, force=lambda t: np.array([math.nan, 1.0, 0.0]), t0=0.06)
    assert (fs == 0.0).all()
    sent = np.array([f for _, f in safe.device.forces])
    assert np.linalg.norm(sent, axis=1).max() <= CAPS.max_force_n * (1 + 1e-12)


def test_stiffness_is_limited_by_the_device_record():
    """A wall ten times stiffer than the device allows: while the hand
    pushes in, the force grows no faster than the device's stiffness times
    the motion (plus the slew allowance), and it drops at once."""
    limits = SafetyLimits(still_for_s=0.001, ramp_s=0.001, slew_n_per_s=0.0)
    k_wall = 10.0 * CAPS.max_stiffness_n_per_mm
    speed = 20.0                                             # [mm/s]
    dev = FlakyDevice(pose=lambda t: (0.0, 0.0, -speed * max(0.0, t - 0.01)))
    safe = SafeDevice(dev, limits=limits)
    safe.open()

    def wall(t):
        depth = speed * max(0.0, t - 0.01)
        return np.array([0.0, 0.0, k_wall * depth])

    ts, rs, fs = _run(safe, 100, force=wall)
    mag = np.linalg.norm(fs, axis=1)
    z = np.array([r.pos_mm[2] for r in rs])
    grow = np.diff(mag)
    moved = np.abs(np.diff(z))
    assert (grow <= CAPS.max_stiffness_n_per_mm * moved + 1e-12).all()
    # it does follow the device's stiffness, not just stay at zero
    np.testing.assert_allclose(mag[-1], CAPS.max_stiffness_n_per_mm * -z[-1], rtol=0.05)
    assert np.linalg.norm(wall(ts[-1])) > 5 * mag[-1]
    _, _, fs = _run(safe, 1, force=lambda t: np.array([0.0, 0.0, 0.01]), t0=0.1)
    assert np.linalg.norm(fs[0]) == pytest.approx(0.01)


def test_safe_start_waits_for_a_still_hand_and_a_small_force_then_ramps():
    lim = SafetyLimits(still_radius_mm=1.0, still_for_s=0.2, start_force_n=0.3, ramp_s=0.5)
    # the hand moves 5 mm/s ... until 0.4 s, then holds still
    dev = FlakyDevice(pose=lambda t: (5.0 * min(t, 0.4), 0.0, 0.0))
    safe = SafeDevice(dev, limits=lim)
    safe.open()
    big = np.array([0.0, 1.0, 0.0])                          # > start_force_n until 0.8 s

    def force(t):
        return big if t < 0.8 else 0.2 * big

    ts, _, fs = _run(safe, 1800, force=force)
    mag = np.linalg.norm(fs, axis=1)
    # nothing while moving nor while the commanded force is large
    assert (mag[ts < 0.8 + lim.still_for_s - DT] == 0.0).all()
    on = np.flatnonzero(mag > 0)[0]
    assert ts[on] == pytest.approx(0.8 + lim.still_for_s, abs=2 * DT)
    # a linear ramp over ramp_s, then full force
    t_on = ts[on - 1]
    ramp = (ts > t_on) & (ts < t_on + lim.ramp_s)
    np.testing.assert_allclose(mag[ramp], 0.2 * (ts[ramp] - t_on) / lim.ramp_s, atol=1e-9)
    assert (mag[ts > t_on + lim.ramp_s + DT] == pytest.approx(0.2))
    assert safe.state == ACTIVE


def test_safe_start_restarts_when_the_hand_moves_while_waiting():
    lim = SafetyLimits(still_radius_mm=1.0, still_for_s=0.2)
    # still for 0.15 s, a 2 mm move, still again
    dev = FlakyDevice(pose=lambda t: (0.0 if t < 0.15 else 2.0, 0.0, 0.0))
    safe = SafeDevice(dev, limits=lim)
    safe.open()
    ts, _, fs = _run(safe, 400, force=lambda t: np.array([0.1, 0.0, 0.0]))
    on = np.flatnonzero(np.linalg.norm(fs, axis=1) > 0)[0]
    assert ts[on] == pytest.approx(0.15 + 0.2, abs=2 * DT)


def test_unplug_zeroes_the_force_the_mouse_takes_over_and_replug_safe_starts():
    lim = SafetyLimits(still_for_s=0.05, ramp_s=0.1, reconnect_s=0.1)
    dev = FlakyDevice(pose=lambda t: (1.0, 2.0, 3.0), unplugged=[(0.5, 1.0)])
    mouse = NullDevice((50.0, 60.0, 70.0))
    safe = SafeDevice(dev, fallback=mouse, limits=lim)
    safe.open()
    ts, rs, fs = _run(safe, 1500, force=lambda t: np.array([0.0, 0.0, 0.2]))
    mag = np.linalg.norm(fs, axis=1)
    before = ts < 0.5
    assert mag[before].max() == pytest.approx(0.2)
    # at once: the first tick of the unplug sends nothing, and from then on
    gone = (ts >= 0.5) & (ts < 1.0)
    assert (mag[gone] == 0.0).all()
    assert all(np.array_equal(r.pos_mm, (50.0, 60.0, 70.0)) for r, g in zip(rs, gone) if g)
    assert safe.unplugs == 1 and safe.replugs == 1
    # the device wrote nothing while gone
    assert all(not 0.5 <= t < 1.0 for t, _ in dev.forces)
    # back (tried every reconnect_s): the pose is the device's, forces after the safe start
    back = np.flatnonzero(ts >= 1.0)
    first = back[[np.array_equal(rs[k].pos_mm, (1.0, 2.0, 3.0)) for k in back]][0]
    assert ts[first] < 1.0 + lim.reconnect_s + DT
    on = first + np.flatnonzero(mag[first:] > 0)[0]
    assert ts[on] - ts[first] == pytest.approx(lim.still_for_s, abs=2 * DT)
    assert safe.state == ACTIVE
    what = [w.split(":")[0] for _, w in safe.take_events()]
    assert what == ["forces-on", "unplugged", "replugged", "forces-on"]


def test_a_device_absent_at_start_is_an_error_naming_it():
    dev = FlakyDevice(unplugged=[(0.0, 1.0)])
    CLOCK[0] = 0.0
    with pytest.raises(BonesimError, match="test-arm"):
        SafeDevice(dev).open()


def test_states_while_unplugged_and_ramping():
    lim = SafetyLimits(still_for_s=0.01, ramp_s=0.1, reconnect_s=0.05)
    dev = FlakyDevice(unplugged=[(0.2, 0.3)])
    safe = SafeDevice(dev, fallback=NullDevice(), limits=lim)
    safe.open()
    assert safe.state == WAITING
    _run(safe, 50)
    assert safe.state == RAMPING and 0 < safe.gain < 1
    _run(safe, 10, t0=0.2)
    assert safe.state == UNPLUGGED and safe.coupled and safe.gain == 0.0


class WallClockFlaky:
    """Unplugged over spans of wall-clock time since it was first opened
    (for the haptic loop's process, which reads it at its own times)."""

    caps = CAPS

    def __init__(self, pos, unplugged):
        self.pos = np.array(pos, float)
        self.unplugged = unplugged
        self.t0 = None

    def _gone(self):
        import time

        if self.t0 is None:
            self.t0 = time.monotonic()
        t = time.monotonic() - self.t0
        return any(a <= t < b for a, b in self.unplugged)

    def open(self):
        if self._gone():
            raise BonesimError("wall-clock arm: not found")

    def read(self, t_s):
        if self._gone():
            raise DeviceDisconnected("wall-clock arm: gone")
        return DeviceReading(self.pos.copy(), np.array([0.0, 0.0, -1.0]))

    def write_force(self, f):
        if self._gone():
            raise DeviceDisconnected("wall-clock arm: gone")

    def close(self):
        pass


@pytest.mark.slow
def test_haptic_loop_hands_over_to_the_mouse_while_unplugged():
    from bonesim.devices.safety import STATES
    from bonesim.io.loading import load_model
    from bonesim.runtime.haptic_loop import HapticLoop

    model = load_model("phantom", "cutting-5mm")
    arm = (0.0, 0.0, 60.0)
    target = np.array([0.0, 10.0, 60.0])
    dev = WallClockFlaky(arm, unplugged=[(0.8, 1.4)])
    loop = HapticLoop(model, device=("device", dev), run_s=2.5, vibration=False)
    try:
        loop.set_target(target, (0.0, 0.0, -1.0))
        loop.start()
        assert loop.wait(30.0)
        smp = loop.samples.read(0, loop.samples.count)
        st = loop.status
        assert int(st["device_unplugs"]) == 1
        assert STATES[int(st["device_state"])] != "unplugged"
        on_mouse = np.all(smp["hand_mm"] == target, axis=1)
        on_arm = np.all(smp["hand_mm"] == arm, axis=1)
        assert on_mouse.sum() > 300 and on_arm.sum() > 1000
        assert (on_mouse | on_arm).all()
        k = np.flatnonzero(on_mouse)
        # one hand-over each way, the mouse in between
        assert np.all(np.diff(k) == 1) and on_arm[:k[0]].all() and on_arm[k[-1] + 1:].all()
        # the mouse moves the tool through the coupling, from where the arm left it
        np.testing.assert_allclose(smp["pos_mm"][k[0]], arm, atol=0.5)
        np.testing.assert_allclose(smp["pos_mm"][k[-1]], target, atol=0.5)
        assert (np.linalg.norm(smp["force_n"][k], axis=1) == 0.0).all()
    finally:
        loop.close()
