"""The instrumented handle on an ADU100, over a pyusb backend stand-in that
answers the box's commands at the transfer level (pyusb's own code runs):
the protocol, the two-point calibration with its prompts, the poller, a
full run where the lever drives the drill, and an unplug."""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.devices import adu100
from bonesim.devices.adu100 import ADU100Handle
from bonesim.devices.config import CONFIG_ENV, calibration, load_config
from bonesim.errors import BonesimError
from bonesim.devices.standins.adu100_usb import FakeADU100, FakeUsbBackend
from tests.bonesim.waiting import wait_until


@pytest.fixture(autouse=True)
def cfg(tmp_path, monkeypatch):
    path = tmp_path / "devices.toml"
    monkeypatch.setenv(CONFIG_ENV, str(path))
    return path


def test_packets_and_answers():
    assert adu100.encode_command("RUN10") == b"\x01RUN10\x00\x00"
    assert adu100.decode_answer(b"\x0101234\x00\x00") == 1234
    assert adu100.decode_answer([1, 0x36, 0x35, 0x35, 0x33, 0x35, 0, 0]) == 65535
    for bad in (b"\x00123", b"\x01abc\x00", b"\x01", b""):
        with pytest.raises(ValueError):
            adu100.decode_answer(bad)
    with pytest.raises(ValueError):
        adu100.encode_command("TOOLONGCMD")


def test_calibration_is_linear_between_the_two_points():
    cal = adu100.calibrate([1000, 60000], [50000, 4000], [30.0, 0.0], [0.0, 180.0])
    np.testing.assert_allclose(adu100.angles_deg(cal, [1000, 60000]), [30.0, 0.0])
    np.testing.assert_allclose(adu100.angles_deg(cal, [50000, 4000]), [0.0, 180.0])
    np.testing.assert_allclose(adu100.angles_deg(cal, [25500, 32000]), [15.0, 90.0])
    with pytest.raises(BonesimError, match="analog input 2 read 7 both"):
        adu100.calibrate([10, 7], [900, 7])


def test_pyusb_finds_reads_and_names_the_box():
    box = FakeADU100(serial="B02597")
    box.analog.update({1: 12345, 2: 54321})
    be = FakeUsbBackend(box)
    assert adu100.connected(be) == ["ADU100 (bus 1 address 17)"]
    h = ADU100Handle(usb_backend=be)
    h.open(poll=False)
    assert h.serial == "B02597" and box.claimed
    np.testing.assert_array_equal(h.read_counts(), [12345, 54321])
    assert box.commands[-2:] == ["RUN10", "RUN20"]
    h.close()
    with pytest.raises(BonesimError, match="no ADU100 connected .*serial X1"):
        ADU100Handle({"serial": "X1"}, usb_backend=be).open()
    with pytest.raises(BonesimError, match="no ADU100 connected"):
        ADU100Handle(usb_backend=FakeUsbBackend()).open()


def test_calibrate_with_prompts_stores_it_per_box(cfg):
    box = FakeADU100(serial="B07777")
    be = FakeUsbBackend(box)
    prompts = []

    def ask(text):
        prompts.append(text)
        if len(prompts) == 1:                     # the user opens the handle ...
            box.analog.update({1: 2000, 2: 61000})
        else:                                     # ... then closes it
            box.analog.update({1: 52000, 2: 3000})

    box.analog.update({1: 30000, 2: 30000})       # wherever it was before
    cal = adu100.run_calibration(ADU100Handle(usb_backend=be), ask)
    assert "Open the handle fully" in prompts[0] and "Close the handle fully" in prompts[1]
    assert cal["open"] == [2000.0, 61000.0] and cal["closed"] == [52000.0, 3000.0]
    stored = calibration("adu100-handle", "B07777")
    assert stored["serial"] == "B07777" and stored["open"] == [2000.0, 61000.0]
    assert calibration("adu100-handle", "default")["closed"] == [52000.0, 3000.0]
    # a handle made without one finds its box's calibration on opening
    h = ADU100Handle(usb_backend=be)
    box.analog.update({1: 27000, 2: 32000})
    h.open(poll=False)
    np.testing.assert_allclose(h.angles, [15.0, 90.0])
    h.close()
    assert load_config()["calibration"]["adu100-handle"].keys() == {"B07777", "default"}


def test_the_calibrate_command_refuses_devices_without_one(capsys):
    from bonesim.cli.main import main

    assert main(["calibrate", "spacemouse"]) == 2
    assert "needs no calibration" in capsys.readouterr().err


@pytest.fixture(scope="module")
def model():
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm")


def test_lever_drives_the_drill_in_a_full_run_and_an_unplug_stops_it(model):
    from bonesim.devices.null import NullDevice
    from bonesim.devices.pedal import PedalGuard
    from bonesim.io.case import load_case
    from tests.bonesim.devices.drive import drive

    box = FakeADU100()
    be = FakeUsbBackend(box)
    cal = adu100.calibrate([2000, 0], [52000, 60000], [30.0, 0.0], [0.0, 180.0])
    h = ADU100Handle({"max_speed_rpm": 80000.0, "reconnect_s": 0.05}, cal, usb_backend=be)
    box.analog.update({1: 2000, 2: 0})                      # lever open
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    into_bone = NullDevice(np.array([23.0, 3.0, -2.0]) + 5.0 * view, view)
    guard = PedalGuard(h)
    run = drive(model, into_bone, 50, pedal=guard)
    assert not run["out"]["drill"].any()
    box.analog[1] = 2000 + 0.75 * 50000                     # squeezed three quarters
    assert wait_until(lambda: h.lever_fraction() == pytest.approx(0.75))
    drive(model, into_bone, 400, t0=0.05, run=run)
    o = run["out"]
    assert o["drill"].all()
    np.testing.assert_allclose(o["speed"], 60000.0)
    assert run["state"].n_removed > 0
    np.testing.assert_allclose(h.angles[0], 7.5)
    assert h.reads > 3
    box.plugged = False                                     # pulled out
    assert wait_until(lambda: h._error is not None)
    drive(model, into_bone, 10, t0=0.5, run=run)
    assert not run["out"]["drill"].any() and guard.unplugs == 1
    box.plugged = True                                      # back, still squeezed
    drive(model, into_bone, 200, t0=0.6, run=run)
    assert guard.connected and not run["out"]["drill"].any()   # not until squeezed anew
    box.analog[1] = 2000
    assert wait_until(lambda: h.lever_fraction() == 0.0)
    drive(model, into_bone, 5, t0=0.8, run=run)
    box.analog[1] = 52000
    assert wait_until(lambda: h.lever_fraction() == 1.0)
    drive(model, into_bone, 5, t0=0.81, run=run)
    assert run["out"]["drill"].all()
    np.testing.assert_allclose(run["out"]["speed"], 80000.0)
    h.close()


def test_a_recorded_handle_run_keeps_its_angles_replays_and_plays_back(model, tmp_path):
    """The handle's calibrated angles go into the session's ``/handle``
    group (at most every HANDLE_RECORD_S, each a read of the box), its
    record and calibration into the header; the run replays bit for bit and
    plays back."""
    from bonesim.devices.null import NullDevice
    from bonesim.devices.pedal import PedalGuard
    from bonesim.devices.registry import device_record
    from bonesim.engine.events import HANDLE_CHANNELS
    from bonesim.io.case import load_case
    from bonesim.runtime.handle_stream import HANDLE_RECORD_S
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify
    from tests.bonesim.devices.drive import drive, finish

    box = FakeADU100(serial="B01234")
    cal = adu100.calibrate([2000, 0], [52000, 60000], [30.0, 0.0], [0.0, 180.0])
    h = ADU100Handle({"max_speed_rpm": 80000.0}, cal, usb_backend=FakeUsbBackend(box))
    box.analog.update({1: 2000, 2: 30000})                  # open; the wheel half way
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    into_bone = NullDevice(np.array([23.0, 3.0, -2.0]) + 5.0 * view, view)
    header = make_header(model, input_device="null", device_record={
        "backend": "null", "pedal": device_record("adu100-handle", h)})
    path = tmp_path / "handle.h5"
    run = drive(model, into_bone, 100, pedal=PedalGuard(h), record=path, header=header)
    box.analog[1] = 2000 + 0.75 * 50000                     # squeezed three quarters
    assert wait_until(lambda: h.lever_fraction() == pytest.approx(0.75))
    drive(model, into_bone, 300, t0=0.1, run=run)
    box.analog[1] = 52000                                   # fully closed
    assert wait_until(lambda: h.lever_fraction() == 1.0)
    drive(model, into_bone, 300, t0=0.4, run=run)
    finish(run)
    h.close()
    s = read_session(path)
    rec = s.header["device_record"]["pedal"]
    assert rec["backend"] == "adu100-handle" and rec["calibration"]["closed"] == [52000.0,
                                                                                 60000.0]
    a, c, t = s.handle["angles_deg"], s.handle["counts"], s.handle["t_s"]
    assert a.shape[1] == HANDLE_CHANNELS and len(t) > 3
    assert (np.diff(t) >= HANDLE_RECORD_S - 1e-12).all() and len(t) <= 0.7 / HANDLE_RECORD_S + 1
    assert np.isin(t, s.samples["t_s"]).all()               # stamped with their steps
    np.testing.assert_array_equal(a[:, :2], adu100.angles_deg(cal, c[:, :2]))
    assert np.isnan(a[:, 2:]).all() and np.isnan(c[:, 2:]).all()
    np.testing.assert_allclose(a[:, 1], 90.0)               # the wheel stayed
    lever = a[:, 0]                                         # 30 deg open .. 0 closed
    assert lever[0] == 30.0 and lever[-1] == 0.0 and np.any(np.isclose(lever, 7.5))
    assert (np.diff(lever) <= 0).all()
    # the drill ran while the lever was squeezed, as recorded (the angles are
    # a sample of the readings every HANDLE_RECORD_S at most)
    on = s.samples["drill"].astype(bool)
    first = t[np.flatnonzero(lever < 30.0)[0]]
    assert not on[s.samples["t_s"] < first - HANDLE_RECORD_S].any() and on[-1]
    assert on[s.samples["t_s"] >= first].all()
    assert len(s.removals["t_s"]) == run["state"].n_removed > 0
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    np.testing.assert_array_equal(p.grid.density > 0, run["state"].grid.density > 0)
    assert p.frame().handle_deg == tuple(a[-1, :2])        # playback shows the angles
    mid = t[len(t) // 2] - s.samples["t_s"][0]
    assert p.frame(mid).handle_deg == tuple(a[len(t) // 2, :2])
    assert p.frame(0.0).handle_deg == (30.0, 90.0)


def test_files_without_the_handle_group_still_read(model, tmp_path):
    """A schema-2 file written before ``/handle`` existed reads with no
    handle rows and replays."""
    import h5py

    from bonesim.io.trajectory import Trajectory
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.reader import read_session, repair_session
    from bonesim.session.replay import verify

    n = 200
    t = np.arange(n) / 1000.0
    pos = np.tile([23.0, 3.0, 8.0], (n, 1))
    traj = Trajectory(t_s=t, pos_mm=pos, axis=np.tile([0, 0, -1.0], (n, 1)),
                      drill=np.ones(n, bool), speed_rpm=np.full(n, 60000.0),
                      direction=np.ones(n, np.int8))
    path = tmp_path / "old.h5"
    run_trajectory(model, traj, surface=False, record=path)
    with h5py.File(path, "r+") as f:
        assert "handle" in f and f["handle/t_s"].shape == (0,)
        del f["handle"]                                     # as an older recorder wrote it
    s = read_session(path)
    assert s.complete and s.handle["t_s"].shape == (0,)
    assert s.handle["angles_deg"].shape[1:] == s.handle["counts"].shape[1:] == (4,)
    assert len(s.samples["t_s"]) == n and verify(s)["ok"]
    again = repair_session(path, tmp_path / "again.h5")     # written with the group
    assert again.handle["t_s"].shape == (0,) and len(again.samples["t_s"]) == n


class CountingHandle:
    """A handle for the haptic loop's process (the USB stand-in's poller
    thread cannot be pickled there; the handle's own readings_into runs): each
    poll is a new reading whose lever
    count is the number of polls, calibrated as ``CAL``; squeezed, so the
    drill runs."""

    reconnect_s = 0.1
    CAL = adu100.calibrate([0, 0], [100000, 50000], [30.0, 0.0], [0.0, 180.0])

    def __init__(self):
        self.handle = None                 # made in the loop's process (it holds a lock)
        self.released = False

    @property
    def reads(self):
        return self.handle.reads

    def open(self):
        self.handle = ADU100Handle({}, self.CAL)

    def poll(self, t_s):
        h = self.handle
        h.reads += 1
        h.counts[:] = (h.reads, 25000.0)
        return True, 50000.0

    def readings_into(self, angles, counts):
        self.handle.readings_into(angles, counts)

    def close(self):
        pass


@pytest.mark.slow
def test_the_haptic_loop_records_a_handles_angles(model, tmp_path):
    """Through the loop's process and the recorder's: the ``handle`` ring
    into ``/handle`` at HANDLE_RECORD_S, each row the reading of its step."""
    from bonesim.runtime.handle_stream import HANDLE_RECORD_S
    from bonesim.session.playback import handle_text
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header
    from bonesim.session.reader import read_session

    loop = HapticLoop(model, device=("null", (0.0, 0.0, 60.0), (0.0, 0.0, -1.0)),
                      run_s=1.0, vibration=False, pedal=CountingHandle())
    path = tmp_path / "loop-handle.h5"
    rec = Recorder(loop, path, make_header(model, input_device="null"), visibility=False)
    try:
        rec.start()
        loop.start()
        assert loop.wait(30.0)
        rec.close()
        latest = loop.status["handle_deg"].copy()
    finally:
        loop.close()
    s = read_session(path)
    t, a, c = s.handle["t_s"], s.handle["angles_deg"], s.handle["counts"]
    # the window's HUD reads the angles last recorded from the loop's status
    np.testing.assert_array_equal(latest, a[-1])
    assert handle_text(latest) == f"{a[-1, 0]:.1f} / 90.0 deg"
    steps = len(s.samples["t_s"])
    assert steps > 100 and np.isin(t, s.samples["t_s"]).all()
    assert (np.diff(t) >= HANDLE_RECORD_S - 1e-12).all()
    assert 0.5 * s.duration_s / HANDLE_RECORD_S < len(t) <= s.duration_s / HANDLE_RECORD_S + 1
    # one poll per step: the count is the step's number (from 1)
    k = np.searchsorted(s.samples["t_s"], t)
    np.testing.assert_array_equal(c[:, 0], k + 1)
    np.testing.assert_array_equal(a[:, :2], adu100.angles_deg(CountingHandle.CAL, c[:, :2]))
    np.testing.assert_allclose(a[:, 1], 90.0)
    assert s.samples["drill"].all()
    from bonesim.session.replay import verify

    report = verify(s)                                      # the loop's run replays
    assert report["ok"], report


def test_probing_puts_the_boxs_own_calibration_in_the_header_record(cfg, monkeypatch):
    """As ``bonesim run --pedal adu100-handle`` does before the header is made:
    the handle made from the config holds the ``default`` calibration; the box
    plugged in is B07777, calibrated on its own, and probing it (pyusb's
    find() over the stand-in as its libusb-1.0 backend) gives that one."""
    import usb.backend.libusb1 as libusb1

    from bonesim.devices import registry
    from bonesim.devices.config import set_calibration

    box = FakeADU100(serial="B07777")
    be = FakeUsbBackend(box)
    monkeypatch.setattr(libusb1, "get_backend", lambda *a, **k: be)
    other = adu100.calibrate([1000, 0], [51000, 60000], [30.0, 0.0], [0.0, 180.0])
    mine = adu100.calibrate([3000, 100], [43000, 50100], [25.0, 0.0], [0.0, 90.0])
    set_calibration("adu100-handle", "default", {**other, "serial": "B00001"})
    set_calibration("adu100-handle", "B07777", {**mine, "serial": "B07777"})
    h = registry.make_device("adu100-handle", pedal_ok=True)
    assert h.calibration["open"] == other["open"]
    assert registry.probe("adu100-handle", h)
    assert h.calibration["serial"] == "B07777" and h.calibration["open"] == mine["open"]
    assert h._dev is None and h._thread is None            # the run opens it itself
    assert box.commands[-2:] == ["RUN10", "RUN20"]           # the twin read the box
    rec = registry.device_record("adu100-handle", h)
    assert rec["caps"] is None and rec["calibration"]["closed_deg"] == [0.0, 90.0]
    assert not registry.probe("pedal", object())           # a pedal has nothing to read
