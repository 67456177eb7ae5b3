"""The OpenHaptics backend through the real pyopenhaptics binding over a
stub of the HD library's C functions, compiled here with gcc: the device's
limits read at opening, a full run (pose in, force out, the force limited
to the device's), an unplug and a replug; and the one-line message when the
vendor library is missing."""
from __future__ import annotations

import ctypes
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.devices.safety import ACTIVE, UNPLUGGED, WAITING, SafetyLimits
from tests.bonesim.waiting import wait_until

ROOT = Path(__file__).resolve().parents[3]


def test_without_the_vendor_library_one_line_names_what_to_install():
    code = ("from bonesim.devices.openhaptics import library_missing; "
            "print(library_missing())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                         check=True).stdout.strip()
    assert out.count("\n") == 0 and "libHD.so" in out and "OpenHaptics" in out


@pytest.fixture(scope="module")
def stub():
    from bonesim.devices.standins.hd_library import load

    return load()


def _rendered(lib):
    v = (ctypes.c_double * 3)()
    lib.stub_rendered(v)
    return np.array(v[:])


def test_opening_reads_the_device_limits_through_the_binding(stub):
    from bonesim.devices.openhaptics import CAPS, OpenHapticsDevice, library_missing

    assert library_missing() is None
    dev = OpenHapticsDevice()
    assert dev.caps == CAPS
    stub.stub_place(1.0, 2.0, 3.0)
    dev.open()
    try:
        assert dev.caps.max_force_n == pytest.approx(0.88)
        assert dev.caps.workspace_mm == (160.0, 120.0, 70.0)
        assert dev.caps.max_stiffness_n_per_mm == pytest.approx(0.39)
        assert "stub" in dev.model
        assert wait_until(lambda: dev.ticks > 20)
        r = dev.read(0.0)
        np.testing.assert_allclose(r.pos_mm, (1.0, 2.0, 3.0))
        np.testing.assert_allclose(r.axis, (0.0, 0.0, -1.0))
    finally:
        dev.close()
    assert stub.stub_running() == 0


@pytest.fixture(scope="module")
def model():
    from bonesim.devices.openhaptics import CAPS
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm", device=CAPS)


# pyopenhaptics' callback wrapper raises KeyError on HD_COMM_ERROR (its error
# table lacks the code); the exception ends the callback inside ctypes, which
# is what an unplug should do, and pytest reports it as unraisable
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_full_run_pose_in_force_out_unplug_and_replug(stub, model, tmp_path):
    from bonesim.devices.openhaptics import OpenHapticsDevice
    from bonesim.devices.registry import device_record, probe
    from bonesim.io.case import load_case
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify
    from tests.bonesim.devices.drive import drive, finish

    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
    view /= np.linalg.norm(view)
    start = np.asarray(cam.focal_mm, float) - 10.0 * view
    # device axes = case axes, device origin at the start
    dev = OpenHapticsDevice({"origin_mm": list(start), "lost_s": 0.05})
    stub.stub_place(0.0, 0.0, 0.0)
    lim = SafetyLimits(still_for_s=0.1, ramp_s=0.1, reconnect_s=0.1)
    probe("touch", dev)                    # as the app does: the device's own record
    header = make_header(model, input_device="touch", device_record=device_record("touch", dev))
    path = tmp_path / "touch.h5"
    run = drive(model, dev, 300, realtime=True, limits=lim, record=path, header=header)
    safe = run["safe"]
    assert safe.state == ACTIVE, safe.take_events() and safe.caps.max_force_n == pytest.approx(0.88)
    np.testing.assert_allclose(run["out"]["hand"][-1], start, atol=1e-9)
    # the hand pushes the stylus 14 mm along the view: into the bone
    stub.stub_place(*(14.0 * view))
    run = drive(model, dev, 300, t0=0.3, run=run, realtime=True, drill=True)
    o = run["out"]
    mag = np.linalg.norm(o["force"], axis=1)
    assert mag.max() == pytest.approx(0.88, rel=1e-9)      # the device's limit, reached
    assert (mag <= 0.88 + 1e-12).all()
    # the arm renders what the safety layer sent last (device axes = case axes)
    assert wait_until(lambda: np.allclose(_rendered(stub), o["force"][-1], atol=1e-12))
    assert run["state"].n_removed > 0
    pos = (ctypes.c_double * 3)()
    stub.stub_position(pos)
    # the stub's passive hand moved under the rendered forces (off its rest point)
    assert np.linalg.norm(np.array(pos[:]) - 14.0 * view) > 0.1
    # unplugged: within lost_s the force is zero and the mouse drives
    stub.stub_unplug(1)
    run = drive(model, dev, 300, t0=0.6, run=run, realtime=True)
    o = run["out"]
    gone = np.flatnonzero(o["state"] == UNPLUGGED)
    assert len(gone) and gone[0] <= 0.05 * 1000 + 5
    assert (o["force"][gone[0]:] == 0.0).all()
    np.testing.assert_array_equal(o["hand"][gone[-1]], (0.0, 0.0, 80.0))
    # plugged back in: found again, and forces wait for the safe start
    stub.stub_unplug(0)
    stub.stub_place(0.0, 0.0, 0.0)
    run = drive(model, dev, 400, t0=0.9, run=run, realtime=True)
    o = run["out"]
    assert safe.replugs == 1 and safe.unplugs == 1
    back = np.flatnonzero(o["state"] != UNPLUGGED)[0]
    assert o["state"][back] == WAITING and o["state"][-1] == ACTIVE
    np.testing.assert_allclose(o["hand"][-1], start, atol=1e-6)
    finish(run)
    # the run (unplug included) replays bit for bit and plays back
    s = read_session(path)
    assert s.header["input"] == "touch" and s.header["device_record"]["backend"] == "touch"
    assert s.header["device_record"]["caps"]["max_force_n"] == pytest.approx(0.88)
    assert len(s.removals["t_s"]) == run["state"].n_removed > 0
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    np.testing.assert_array_equal(p.grid.density > 0, run["state"].grid.density > 0)


@pytest.mark.slow
def test_a_run_through_the_haptic_loop_records_the_devices_own_limits(stub, tmp_path,
                                                                      monkeypatch):
    """The App's path: the backend is probed in this process (the stub's
    limits, not the Touch defaults, go into the model and the header), then
    the haptic loop's own process opens the stub again (found there through
    LD_LIBRARY_PATH) and publishes the record it opened with; the run
    replays bit for bit and plays back."""
    import os

    from bonesim.devices import registry
    from bonesim.devices.config import CONFIG_ENV
    from bonesim.devices.openhaptics import CAPS
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify

    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "devices.toml"))
    folder = str(Path(stub._name).parent)
    monkeypatch.setenv("LD_LIBRARY_PATH",
                       folder + os.pathsep + os.environ.get("LD_LIBRARY_PATH", ""))
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    rest = np.array([23.0, 3.0, -2.0]) + 3.0 * view             # the stylus in the cortex
    dev = registry.make_device("touch", {"origin_mm": list(rest)})
    assert dev.caps == CAPS and CAPS.max_force_n == pytest.approx(3.3)
    assert registry.probe("touch", dev)
    assert dev._id is None and stub.stub_running() == 0          # closed again
    own = (0.88, 160.0, 120.0, 70.0, 0.39)            # hd_stub.c's continuous force
    assert (dev.caps.max_force_n, *dev.caps.workspace_mm, dev.caps.max_stiffness_n_per_mm) \
        == pytest.approx(own)
    assert not registry.probe("simulated-hand", registry.make_device("simulated-hand"))
    model = load_model("phantom", "cutting-5mm", device=dev.caps)
    header = make_header(model, input_device="touch",
                         device_record=registry.device_record("touch", dev))
    path = tmp_path / "touch-loop.h5"
    loop = HapticLoop(model, device=("device", dev), run_s=1.5, vibration=False)
    rec = Recorder(loop, path, header)
    try:
        rec.start()
        loop.set_drill(True, speed_rpm=60000.0)
        loop.start()
        assert loop.wait(30.0)
        rec.close()
        opened = loop.status["device_caps"].copy()
        n_removed = loop.state.n_removed
    finally:
        loop.close()
    s = read_session(path)
    c = s.header["device_record"]["caps"]
    assert (c["max_force_n"], *c["workspace_mm"], c["max_stiffness_n_per_mm"]) \
        == pytest.approx(own)
    assert s.header["device"]["max_force_n"] == pytest.approx(0.88)
    # the loop's process opened the device with the record the header holds
    np.testing.assert_allclose(opened, [c["max_force_n"], *c["workspace_mm"],
                                        c["max_stiffness_n_per_mm"]])
    assert n_removed > 0 and len(s.removals["t_s"]) == n_removed
    assert np.linalg.norm(s.samples["force_n"], axis=1).max() <= 0.88 + 1e-12
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    assert not np.array_equal(p.grid.density, model.grid.density)
