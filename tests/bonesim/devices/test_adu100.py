"""The instrumented handle on an ADU100, over a pyusb backend stand-in that
answers the box's commands at the transfer level (pyusb's own code runs):
the protocol, the two-point calibration with its prompts, the poller, a
full run where the lever drives the drill, and an unplug."""
from __future__ import annotations

import time

import numpy as np
import pytest

from bonesim.devices import adu100
from bonesim.devices.adu100 import ADU100Handle
from bonesim.devices.config import CONFIG_ENV, calibration, load_config
from bonesim.errors import BonesimError
from bonesim.devices.standins.adu100_usb import FakeADU100, FakeUsbBackend


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


def _wait(pred, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.002)
    return False


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
    assert _wait(lambda: h.lever_fraction() == pytest.approx(0.75))
    drive(model, into_bone, 400, t0=0.05, run=run)
    o = run["out"]
    assert o["drill"].all()
    np.testing.assert_allclose(o["speed"], 60000.0)
    assert run["state"].n_removed > 0
    np.testing.assert_allclose(h.angles[0], 7.5)
    assert h.reads > 3
    box.plugged = False                                     # pulled out
    assert _wait(lambda: h._error is not None)
    drive(model, into_bone, 10, t0=0.5, run=run)
    assert not run["out"]["drill"].any() and guard.unplugs == 1
    box.plugged = True                                      # back, still squeezed
    drive(model, into_bone, 200, t0=0.6, run=run)
    assert guard.connected and not run["out"]["drill"].any()   # not until squeezed anew
    box.analog[1] = 2000
    assert _wait(lambda: h.lever_fraction() == 0.0)
    drive(model, into_bone, 5, t0=0.8, run=run)
    box.analog[1] = 52000
    assert _wait(lambda: h.lever_fraction() == 1.0)
    drive(model, into_bone, 5, t0=0.81, run=run)
    assert run["out"]["drill"].all()
    np.testing.assert_allclose(run["out"]["speed"], 80000.0)
    h.close()
