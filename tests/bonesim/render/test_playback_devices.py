"""Runs recorded with every device backend replay bit for bit and play back
drawn offscreen: the simulated hand, the SpaceMouse and the foot pedal (hidapi stand-in), the
ADU100 handle (pyusb backend stand-in) and the Touch (HD library stub). The
runs go through the in-process servo driver of the device tests
(``tests/bonesim/devices/drive.py``): the stand-ins live in this process.
(Runs through the haptic loop's own process: the simulated hand in
``tests/bonesim/devices/test_registry.py``, the Touch stub in
``tests/bonesim/devices/test_openhaptics.py``.)"""
from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow
SIZE = (320, 240)
BACKENDS = ("simulated-hand", "spacemouse", "pedal", "adu100-handle", "touch")


def _run(name, model, path, tmp):
    """Record a short drilling run made with backend ``name``; returns the
    number of voxels it removed."""
    from bonesim.devices.null import NullDevice
    from bonesim.devices.pedal import FootPedal, PedalGuard
    from bonesim.devices.registry import device_record
    from bonesim.devices.safety import SafetyLimits
    from bonesim.io.case import load_case
    from bonesim.session.header import make_header
    from tests.bonesim.devices.drive import drive, finish

    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
    view /= np.linalg.norm(view)
    cortex = np.array([23.0, 3.0, -2.0])
    kw, dev, pedal, rec = {}, None, None, None
    with pytest.MonkeyPatch.context() as mp:
        if name == "simulated-hand":
            from bonesim.devices.simulated_backend import SimulatedHandBackend

            dev = SimulatedHandBackend({"rest_mm": list(cortex + 3.0 * view)})
            rec = device_record(name, dev)
        elif name == "spacemouse":
            from bonesim.devices.spacemouse import SpaceMouse
            from bonesim.devices.standins.hid_bus import install

            bus = install(mp)
            bus.plug(b"/dev/hidraw3", 0x256F, 0xC635)
            right = np.cross(view, cam.up)
            right /= np.linalg.norm(right)
            frame = [list(right), list(np.cross(-view, right)), list(-view)]
            start = np.asarray(cam.focal_mm, float) - 10.0 * view
            dev = SpaceMouse({"start_mm": list(start), "axis": list(view), "frame": frame,
                              "translation_mm_s": 20.0})
            rec = device_record(name, dev)
            push = bytes([1]) + bytes(4) + (350).to_bytes(2, "little")   # z: into the view
            kw["n"] = 1500

            def before(k, t):                 # push along the device z: into the bone
                if k % 16 == 0:
                    bus.send(b"/dev/hidraw3", push)

            kw["before"] = before
        elif name == "pedal":
            from bonesim.devices.standins.hid_bus import install

            bus = install(mp)
            bus.plug(b"/dev/hidraw5", 0x05F3, 0x00FF)
            bus.send(b"/dev/hidraw5", bytes.fromhex("0200"))      # the drill pedal held
            pedal = FootPedal()
            rec = {"backend": "null", "pedal": device_record(name, pedal)}
        elif name == "adu100-handle":
            from bonesim.devices import adu100
            from bonesim.devices.standins.adu100_usb import FakeADU100, FakeUsbBackend

            box = FakeADU100()
            box.analog.update({1: 52000, 2: 30000})               # squeezed; wheel 90 deg
            cal = adu100.calibrate([2000, 0], [52000, 60000], [30.0, 0.0], [0.0, 180.0])
            pedal = adu100.ADU100Handle({}, cal, usb_backend=FakeUsbBackend(box))
            rec = {"backend": "null", "pedal": device_record(name, pedal)}
        elif name == "touch":
            from bonesim.devices.openhaptics import OpenHapticsDevice
            from bonesim.devices.registry import probe
            from bonesim.devices.standins.hd_library import load

            lib = load()
            lib.stub_place(0.0, 0.0, 0.0)
            dev = OpenHapticsDevice({"origin_mm": list(cortex + 3.0 * view)})
            probe(name, dev)
            rec = device_record(name, dev)
            kw.update(realtime=True, limits=SafetyLimits(still_for_s=0.05, ramp_s=0.05))
        if dev is None:
            dev = NullDevice(cortex + 5.0 * view, view)
        header = make_header(model, input_device=name if pedal is None else "null",
                             device_record=rec)
        run = drive(model, dev, kw.pop("n", 500), drill=pedal is None, record=path,
                    header=header,
                    pedal=None if pedal is None else PedalGuard(pedal), **kw)
        n = run["state"].n_removed
        finish(run)
        if pedal is not None:
            pedal.close()
    return n


@pytest.fixture(scope="module")
def sessions(gl_info, tmp_path_factory):
    from bonesim.io.loading import load_model

    model = load_model("phantom", "cutting-5mm")
    out = {}
    for name in BACKENDS:
        tmp = tmp_path_factory.mktemp(name)
        path = tmp / "run.h5"
        out[name] = (path, _run(name, model, path, tmp))
    return out


@pytest.mark.parametrize("name", BACKENDS)
def test_a_run_made_with_each_backend_plays_back_drawn(sessions, name):
    from bonesim.render.playback import PlaybackView
    from bonesim.render.scene import Scene
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify

    path, n_removed = sessions[name]
    s = read_session(path)
    rec = s.header["device_record"]
    assert (rec.get("pedal") or rec)["backend"] == name
    assert n_removed > 0 and len(s.removals["t_s"]) == n_removed
    if name == "adu100-handle":
        assert len(s.handle["t_s"]) > 0 and (s.handle["angles_deg"][:, 0] == 0.0).all()
    report = verify(s)                                     # replays bit for bit
    assert report["ok"], report
    player = Player(s)
    scene = Scene.from_model(player.model, player.surface, size=SIZE, visible_subset=False)
    try:
        v = PlaybackView(scene, player, video=True)
        t0 = float(s.samples["t_s"][0])
        v.show(t0)
        before = player.surface.n_triangles
        t = t0 + s.duration_s
        v.show(t)
        i = len(s.samples["t_s"]) - 1
        m = scene._burr.GetUserMatrix()
        assert [m.GetElement(r, 3) for r in range(3)] == pytest.approx(s.samples["pos_mm"][i])
        assert f"removed: {n_removed:,} voxels" in scene.hud_text, scene.hud_text
        assert scene.surface is player.surface
        assert scene._buffers.n_full == player.surface.n_triangles != before
        assert scene.image().std() > 0                     # something was drawn
        if name == "adu100-handle":                        # the handle's angles, shown
            assert "handle: 0.0 / 90.0 deg" in scene.hud_text, scene.hud_text
        else:
            assert "handle" not in scene.hud_text
    finally:
        scene.close()
