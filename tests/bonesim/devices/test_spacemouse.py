"""The SpaceMouse backend over a stand-in for the hidapi binding: report
parsing (recorded bytes of the separate and the combined layouts), matching
by USB id, hot-plug, and full servo runs (pose in, force out)."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.devices import spacemouse
from bonesim.devices.safety import ACTIVE, UNPLUGGED
from bonesim.errors import BonesimError
from tests.bonesim.devices.drive import drive
from bonesim.devices.standins.hid_bus import install

COMPACT = (0x256F, 0xC635)
WIRELESS = (0x256F, 0xC62E)
PATH = b"/dev/hidraw3"
# a SpaceNavigator-class capture: at rest, a small rotation, button 1 down/up
REST_T = bytes.fromhex("01000000000000")
ROT = bytes.fromhex("020000e2ff0000")
BTN1_DOWN = bytes.fromhex("030100")
BTN_UP = bytes.fromhex("030000")


def _i16(v):
    return (v & 0xFFFF).to_bytes(2, "little")


def t_report(x, y, z):
    return bytes([1]) + _i16(x) + _i16(y) + _i16(z)


def tr_report(x, y, z, rx, ry, rz):
    return bytes([1]) + b"".join(_i16(v) for v in (x, y, z, rx, ry, rz))


def test_reports_parse_for_both_layouts_and_garbage_is_named():
    assert spacemouse.parse_report(list(REST_T)) == ("t", (0, 0, 0))
    assert spacemouse.parse_report(list(ROT)) == ("r", (0, -30, 0))
    assert spacemouse.parse_report(list(BTN1_DOWN)) == ("buttons", 1)
    assert spacemouse.parse_report(list(bytes.fromhex("030300"))) == ("buttons", 3)
    assert spacemouse.parse_report(list(tr_report(350, -350, 12, -1, 0, 300))) == \
        ("tr", (350, -350, 12, -1, 0, 300))
    for junk in ([], [1, 2, 3], [2, 0], [9, 1, 2, 3, 4, 5, 6], [0x17, 100]):
        kind, why = spacemouse.parse_report(junk)
        assert kind is None and isinstance(why, str)


def test_only_known_usb_ids_match_and_a_missing_device_is_named(monkeypatch):
    bus = install(monkeypatch)
    bus.plug(b"/dev/hidraw0", 0x046D, 0xC31C, product="Keyboard")
    with pytest.raises(BonesimError, match="no SpaceMouse connected .*256f:c635"):
        spacemouse.SpaceMouse().open()
    bus.plug(PATH, *COMPACT, product="SpaceMouse Compact")
    assert spacemouse.connected() == ["SpaceMouse Compact (256f:c635)"]
    from bonesim.devices.registry import describe

    assert describe("spacemouse")["connected"] == ["SpaceMouse Compact (256f:c635)"]
    assert describe("pedal")["connected"] == []
    sm = spacemouse.SpaceMouse()
    sm.open()
    assert sm.link.model.name == "SpaceMouse Compact"
    assert sm.link.info["product_string"] == "SpaceMouse Compact"
    with pytest.raises(BonesimError, match="unknown setting"):
        spacemouse.SpaceMouse({"speed": 3})


@pytest.fixture(scope="module")
def model():
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm", device=spacemouse.CAPS)


def _setup(monkeypatch, ids=COMPACT, **settings):
    from bonesim.io.case import load_case

    bus = install(monkeypatch)
    bus.plug(PATH, *ids)
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
    view /= np.linalg.norm(view)
    back = -view
    right = np.cross(view, cam.up)
    right /= np.linalg.norm(right)
    frame = [list(right), list(np.cross(back, right)), list(back)]
    start = np.asarray(cam.focal_mm, float) - 10.0 * view
    s = {"start_mm": list(start), "axis": list(view), "frame": frame, **settings}
    return bus, spacemouse.SpaceMouse(s), right, view, start


def test_translation_rotation_and_camera_toggle_from_recorded_reports(monkeypatch, model):
    bus, sm, right, view, start = _setup(monkeypatch)

    def reports(k, t):
        if k == 0:                                   # half deflection to the right
            bus.send(PATH, t_report(175, 0, 0), bytes.fromhex("02000000000000"))
        elif 16 <= k < 500 and k % 16 == 0:          # the device repeats at ~60 Hz
            bus.send(PATH, t_report(175, 0, 0))
        elif k == 500:
            bus.send(PATH, REST_T, BTN1_DOWN)        # at rest; button 1: camera mode
        elif k == 501:
            bus.send(PATH, BTN_UP, t_report(0, 0, 350))     # cap pushed down
        elif 502 <= k < 700 and k % 16 == 0:
            bus.send(PATH, t_report(0, 0, 350))

    run = drive(model, sm, 700, before=reports)
    o = run["out"]
    assert run["safe"].state == ACTIVE                # no force to ramp: active at once
    # 0.5 s at half of 40 mm/s, along the view's right
    moved = o["hand"][499] - start
    np.testing.assert_allclose(moved, 0.5 * 40.0 * 0.499 * right, atol=1e-9)
    # camera mode: the tool holds, the push down asks the camera to move into the view
    np.testing.assert_array_equal(o["hand"][699], o["hand"][499])
    assert sm.camera_mode
    np.testing.assert_allclose(sm.camera_rate[:3], 60.0 * view, atol=1e-9)
    np.testing.assert_allclose(o["axis"][-1], view, atol=1e-12)     # no rotation asked
    bus.send(PATH, BTN1_DOWN, BTN_UP, t_report(0, 0, 0))
    drive(model, sm, 5, t0=0.7, run=run)
    assert not sm.camera_mode and not sm.camera_rate.any()


def test_combined_report_turns_the_tool_and_garbage_is_ignored(monkeypatch, model):
    bus, sm, right, view, start = _setup(monkeypatch, ids=WIRELESS, rotation_deg_s=90.0)

    def reports(k, t):
        if k % 16 == 0 and k < 1000:                 # full tilt about device x (right)
            bus.send(PATH, tr_report(0, 0, 0, 350, 0, 0), [0x17, 100], [1, 2])

    run = drive(model, sm, 1000, before=reports)
    o = run["out"]
    # +90 deg/s about the view's right for 1 s: the drill axis tips from the
    # view toward the screen's up (right x view = up)
    turned = np.degrees(np.arccos(np.clip(o["axis"][-1] @ view, -1, 1)))
    assert turned == pytest.approx(90.0 * 0.999, abs=0.01)
    np.testing.assert_allclose(o["axis"][-1] @ right, 0.0, atol=1e-9)
    up = np.cross(-view, right)
    assert o["axis"][-1] @ up > 0.99
    assert sm.ignored == 2 * 63
    np.testing.assert_allclose(o["hand"][-1], start, atol=1e-12)


def test_pushing_into_bone_with_the_drill_on_gives_force_and_removal(monkeypatch, model):
    bus, sm, right, view, start = _setup(monkeypatch, translation_mm_s=20.0)

    def reports(k, t):
        if k % 16 == 0:
            bus.send(PATH, t_report(0, 0, 350))      # cap pushed down: into the picture

    run = drive(model, sm, 1500, before=reports, drill=True)
    o = run["out"]
    mag = np.linalg.norm(o["force"], axis=1)
    assert mag.max() > 0.1                            # the bone pushed back
    assert run["state"].n_removed > 0
    # the hand went 30 mm in; the coupling kept the tool resting on the bone behind it
    assert (o["hand"][-1] - start) @ view == pytest.approx(20.0 * 1.499, abs=1e-6)
    assert (o["pos"][-1] - start) @ view < (o["hand"][-1] - start) @ view - 0.5


def test_unplug_hands_over_and_replug_re_enumerates(monkeypatch, model):
    bus, sm, right, view, start = _setup(monkeypatch)

    def events(k, t):
        if k % 16 == 0:
            bus.send(PATH, t_report(350, 0, 0))
        if k == 300:
            bus.unplug(PATH)
        if k == 900:
            bus.plug(PATH, *COMPACT)

    n_enum = len(bus.calls)
    run = drive(model, sm, 1600, before=events)
    o, safe = run["out"], run["safe"]
    assert (o["state"][300:900] == UNPLUGGED).all()
    np.testing.assert_array_equal(o["hand"][300:900], np.tile([0.0, 0.0, 80.0], (600, 1)))
    assert safe.unplugs == 1 and safe.replugs == 1 and o["state"][-1] == ACTIVE
    assert len(bus.calls) - n_enum >= 2               # looked for again, found
    # the tool moves on from where the device's pose had got to
    back = np.flatnonzero(o["state"] == ACTIVE)
    back = back[back > 900][0]
    assert back <= 900 + 500 + 1
    assert (o["hand"][-1] - o["hand"][back]) @ right > 0


def test_a_hung_report_stream_stops_the_tool(monkeypatch, model):
    bus, sm, right, view, start = _setup(monkeypatch)
    bus.send(PATH, t_report(350, 0, 0))               # one report, then silence
    run = drive(model, sm, 600)
    o = run["out"]
    travel = (o["hand"][-1] - start) @ right
    assert travel == pytest.approx(40.0 * 0.25, abs=0.05)   # report_timeout_s of motion


def test_a_recorded_spacemouse_run_replays_and_plays_back(monkeypatch, model, tmp_path):
    from bonesim.devices.registry import device_record
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify
    from tests.bonesim.devices.drive import finish

    bus, sm, right, view, start = _setup(monkeypatch, translation_mm_s=20.0)
    header = make_header(model, input_device="spacemouse",
                         device_record=device_record("spacemouse", sm))

    def reports(k, t):
        if k % 16 == 0:
            bus.send(PATH, t_report(0, 0, 350))

    path = tmp_path / "sm.h5"
    run = drive(model, sm, 1500, before=reports, drill=True, record=path, header=header)
    finish(run)
    s = read_session(path)
    assert s.header["device_record"]["backend"] == "spacemouse"
    assert s.header["device_record"]["settings"]["translation_mm_s"] == 20.0
    assert len(s.removals["t_s"]) == run["state"].n_removed > 0
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    np.testing.assert_array_equal(p.grid.density > 0, run["state"].grid.density > 0)
