"""The foot pedal over a stand-in for the hidapi binding: the IN-USB-2's
recorded reports, a pedal described in the config, and a full run where the
pedal drills, is unplugged (the drill stops at once) and comes back (the
drill stays off until pressed again)."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.devices import pedal as pedal_mod
from bonesim.devices.pedal import FootPedal, PedalGuard
from bonesim.errors import BonesimError
from tests.bonesim.devices.drive import drive
from bonesim.devices.standins.hid_bus import install

IN_USB_2 = (0x05F3, 0x00FF)
PATH = b"/dev/hidraw5"
# recorded IN-USB-2 reports: two bytes, little-endian mask (1 left, 2 middle, 4 right)
RELEASED, LEFT, MIDDLE, RIGHT = (bytes.fromhex(h) for h in ("0000", "0100", "0200", "0400"))
MIDDLE_RIGHT = bytes.fromhex("0600")


def test_in_usb_2_reports_give_drill_and_speed_steps(monkeypatch):
    bus = install(monkeypatch)
    bus.plug(PATH, *IN_USB_2, product="VEC USB Footpedal")
    assert pedal_mod.connected() == ["Infinity IN-USB-2 (05f3:00ff)"]
    p = FootPedal({"speed_step_rpm": 10000.0, "max_speed_rpm": 75000.0})
    p.open()
    assert p.poll(0.0) == (False, None)
    bus.send(PATH, MIDDLE)
    assert p.poll(0.001) == (True, None)
    assert p.poll(0.002) == (True, None)                    # held
    bus.send(PATH, MIDDLE_RIGHT)                            # faster while drilling
    assert p.poll(0.003) == (True, 70000.0)
    bus.send(PATH, MIDDLE, MIDDLE_RIGHT, MIDDLE)            # a second press: clamped
    assert p.poll(0.004) == (True, 75000.0)
    bus.send(PATH, RELEASED, LEFT, RELEASED, LEFT, RELEASED)
    assert p.poll(0.005) == (False, 55000.0)
    bus.send(PATH, [7])                        # all three at once, in a one-byte report
    assert p.poll(0.0055) == (True, 55000.0)
    assert p.ignored == 0
    bus.send(PATH, RELEASED, [])               # an empty read: nothing more pending
    assert p.poll(0.006) == (False, 55000.0)


def test_a_pedal_described_in_the_config(monkeypatch):
    bus = install(monkeypatch)
    bus.plug(PATH, 0x1234, 0xABCD)
    p = FootPedal({"usb_id": "1234:abcd", "report_byte": 2, "drill_bit": 0x10})
    p.open()
    bus.send(PATH, [0, 0, 0x10], [0])
    assert p.poll(0.0) == (True, None) and p.ignored == 1
    with pytest.raises(BonesimError, match="usb_id"):
        FootPedal({"usb_id": "xyz"})
    with pytest.raises(BonesimError, match="no foot pedal connected .*05f3:00ff"):
        FootPedal().open()


@pytest.fixture(scope="module")
def model():
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm")


def test_pedal_drills_stops_at_an_unplug_and_rearms_after_the_return(monkeypatch, model):
    from bonesim.devices.null import NullDevice
    from bonesim.io.case import load_case

    bus = install(monkeypatch)
    bus.plug(PATH, *IN_USB_2)
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    into_bone = NullDevice(np.array([23.0, 3.0, -2.0]) + 5.0 * view, view)
    guard = PedalGuard(FootPedal({"reconnect_s": 0.1}))

    def foot(k, t):
        if k == 10:
            bus.send(PATH, MIDDLE)                          # press and hold
        if k == 300:
            bus.unplug(PATH)
        if k == 500:
            bus.plug(PATH, *IN_USB_2)
            bus.send(PATH, MIDDLE)                          # still held down on return
        if k == 800:
            bus.send(PATH, RELEASED, MIDDLE)                # lifted and pressed again

    run = drive(model, into_bone, 1000, before=foot, pedal=guard)
    o = run["out"]
    assert not o["drill"][:10].any() and o["drill"][10:300].all()
    assert not o["drill"][300:800].any()                    # gone, then not re-armed
    assert o["drill"][800:].all()
    assert guard.unplugs == 1 and guard.connected
    assert run["state"].n_removed > 0


def test_a_recorded_pedal_run_replays_and_plays_back(monkeypatch, model, tmp_path):
    """A run whose drill the pedal drove (an unplug included) replays bit for
    bit and plays back; a pedal has no angles, so ``/handle`` stays empty."""
    from bonesim.devices.null import NullDevice
    from bonesim.devices.registry import device_record
    from bonesim.io.case import load_case
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify
    from tests.bonesim.devices.drive import finish

    bus = install(monkeypatch)
    bus.plug(PATH, *IN_USB_2)
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    into_bone = NullDevice(np.array([23.0, 3.0, -2.0]) + 5.0 * view, view)
    pedal = FootPedal({"reconnect_s": 0.1})
    header = make_header(model, input_device="null", device_record={
        "backend": "null", "pedal": device_record("pedal", pedal)})

    def foot(k, t):
        if k == 10:
            bus.send(PATH, MIDDLE_RIGHT)                    # drill, one step faster
        if k == 300:
            bus.unplug(PATH)
        if k == 450:
            bus.plug(PATH, *IN_USB_2)
            bus.send(PATH, RELEASED, MIDDLE)

    path = tmp_path / "pedal.h5"
    run = drive(model, into_bone, 700, before=foot, pedal=PedalGuard(pedal), record=path,
                header=header)
    finish(run)
    s = read_session(path)
    assert s.header["device_record"]["pedal"]["backend"] == "pedal"
    on = s.samples["drill"].astype(bool)
    np.testing.assert_array_equal(on, run["out"]["drill"])
    assert on[10:300].all() and not on[300:450].any() and on[-1]
    assert (s.samples["speed_rpm"][on] == 65000.0).all()
    assert len(s.handle["t_s"]) == 0
    assert len(s.removals["t_s"]) == run["state"].n_removed > 0
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    np.testing.assert_array_equal(p.grid.density > 0, run["state"].grid.density > 0)


class WallClockPedal:
    """A pedal held down from its opening, unplugged after ``gone_s`` of wall
    clock (for the haptic loop's process)."""

    reconnect_s = 0.1

    def __init__(self, gone_s):
        self.gone_s = gone_s
        self.t0 = None
        self.released = False

    def open(self):
        import time

        if self.t0 is None:
            self.t0 = time.monotonic()
        elif time.monotonic() - self.t0 >= self.gone_s:
            raise BonesimError("pedal: not found")

    def poll(self, t_s):
        import time

        from bonesim.devices.interface import DeviceDisconnected

        if time.monotonic() - self.t0 >= self.gone_s:
            raise DeviceDisconnected("pedal: gone")
        return True, 45000.0

    def close(self):
        pass


@pytest.mark.slow
def test_the_haptic_loop_takes_drill_and_speed_from_the_pedal(model):
    from bonesim.runtime.haptic_loop import HapticLoop

    loop = HapticLoop(model, device=("null", (0.0, 0.0, 60.0), (0.0, 0.0, -1.0)),
                      run_s=1.0, vibration=False, pedal=WallClockPedal(0.5))
    try:
        loop.set_drill(False, speed_rpm=60000.0)
        loop.start()
        assert loop.wait(30.0)
        smp = loop.samples.read(0, loop.samples.count)
        assert int(loop.status["pedal"]) == 2                       # unplugged at the end
    finally:
        loop.close()
    on = smp["drill"].astype(bool)
    assert on[0] and not on[-1] and on.sum() > 100
    k = np.flatnonzero(~on)[0]
    assert on[:k].all() and not on[k:].any()                # on, then off for good
    assert (smp["speed_rpm"][:k] == 45000.0).all()
