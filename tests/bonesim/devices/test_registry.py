"""Device registry, the user's device config, ``bonesim devices``, and a run
made with a registered backend: its record in the header, replayed bit for
bit and played back."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bonesim.devices import config, registry
from bonesim.errors import BonesimError


@pytest.fixture()
def cfg_file(tmp_path, monkeypatch):
    path = tmp_path / "conf" / "devices.toml"
    monkeypatch.setenv(config.CONFIG_ENV, str(path))
    return path


def test_config_path_follows_the_env_var_then_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv(config.CONFIG_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert config.config_path() == tmp_path / "bonesim" / "devices.toml"
    monkeypatch.setenv(config.CONFIG_ENV, str(tmp_path / "x.toml"))
    assert config.config_path() == tmp_path / "x.toml"


def test_config_round_trip_settings_and_calibrations(cfg_file):
    assert config.load_config() == {"devices": {}, "calibration": {}}
    cfg = {"devices": {"simulated-hand": {"rest_mm": [1.0, 2.5, -3.0]},
                       "spacemouse": {"translation_mm_s": 40.0, "name": 'a "q"',
                                      "invert": True, "n": 3}},
           "calibration": {}}
    config.save_config(cfg)
    config.set_calibration("adu100-handle", "B02345", {"open": [10.0, 200.0],
                                                     "closed": [230.0, 5.0]})
    back = config.load_config()
    assert back["devices"] == cfg["devices"]
    assert config.calibration("adu100-handle", "B02345") == {"open": [10.0, 200.0],
                                                            "closed": [230.0, 5.0]}
    assert config.calibration("adu100-handle", "other") is None
    assert config.device_settings("spacemouse")["translation_mm_s"] == 40.0


@pytest.mark.parametrize("text, words", [
    ("[devices\n", "malformed TOML"),
    ("[gadgets.x]\na = 1\n", "unknown table 'gadgets'"),
    ("devices = 3\n", "must be a table"),
    ("[devices]\nspacemouse = 3\n", "devices.spacemouse"),
])
def test_a_bad_config_names_the_file_and_the_key(cfg_file, text, words):
    cfg_file.parent.mkdir(parents=True)
    cfg_file.write_text(text)
    with pytest.raises(BonesimError, match=words) as exc:
        config.load_config()
    assert str(cfg_file) in str(exc.value)


def test_registry_lists_backends_and_makes_them_with_the_user_settings(cfg_file):
    names = registry.backend_names()
    assert names[0] == registry.DEFAULT_DEVICE == "mouse" and "simulated-hand" in names
    d = registry.describe("simulated-hand")
    assert d["library"] == "ok" and d["connected"] and d["needs"]
    with pytest.raises(BonesimError, match="unknown device 'nope'"):
        registry.make_device("nope")
    dev = registry.make_device("simulated-hand", start_mm=(1.0, 2.0, 3.0))
    np.testing.assert_array_equal(dev.pos_mm, (1.0, 2.0, 3.0))
    config.save_config({"devices": {"simulated-hand": {"rest_mm": [4.0, 5.0, 6.0]}},
                        "calibration": {}})
    dev = registry.make_device("simulated-hand", start_mm=(1.0, 2.0, 3.0))
    np.testing.assert_array_equal(dev.pos_mm, (4.0, 5.0, 6.0))     # the config wins
    config.save_config({"devices": {"simulated-hand": {"rest_m": [4.0, 5.0, 6.0]}},
                        "calibration": {}})
    with pytest.raises(BonesimError, match="unknown setting"):
        registry.make_device("simulated-hand")
    rec = registry.device_record("mouse")
    assert rec["backend"] == "mouse" and rec["caps"]["max_force_n"] is None


def test_devices_command_lists_without_hardware(cfg_file, capsys):
    from bonesim.cli.main import main

    assert main(["devices", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["config"] == str(cfg_file)
    assert [b["name"] for b in out["backends"]] == registry.backend_names()
    assert main(["devices"]) == 0
    text = capsys.readouterr().out
    assert "simulated-hand" in text and "needs:" in text and str(cfg_file) in text


def test_run_refuses_a_device_with_the_headless_main_job(cfg_file, capsys):
    from bonesim.cli.main import main

    assert main(["run", "--offscreen", "--device", "simulated-hand"]) == 2
    assert "--device needs the live simulator" in capsys.readouterr().err


@pytest.mark.slow
def test_a_run_with_a_device_backend_records_it_replays_and_plays_back(cfg_file, tmp_path):
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify

    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    rest = np.array([23.0, 3.0, -2.0]) + 3.0 * view              # in the cortex
    dev = registry.make_device("simulated-hand", {"rest_mm": list(rest)})
    model = load_model("phantom", "cutting-5mm", device=dev.caps)
    path = tmp_path / "dev.h5"
    loop = HapticLoop(model, device=("device", dev), run_s=1.5, vibration=False)
    header = make_header(model, input_device="simulated-hand",
                         device_record=registry.device_record("simulated-hand", dev))
    rec = Recorder(loop, path, header)
    try:
        rec.start()
        loop.set_drill(True, speed_rpm=60000.0)
        loop.start()
        assert loop.wait(30.0)
        rec.close()
        n_removed = loop.state.n_removed
    finally:
        loop.close()
    s = read_session(path)
    h = s.header
    assert h["input"] == "simulated-hand"
    assert h["device"]["max_force_n"] == dev.caps.max_force_n
    assert h["device_record"]["caps"]["workspace_mm"] == list(dev.caps.workspace_mm)
    assert h["device_record"]["settings"]["rest_mm"] == pytest.approx(list(rest))
    assert n_removed > 0 and len(s.removals["t_s"]) == n_removed
    # the forces recorded are what the safety layer let through: off while
    # the hand rests pressed into the bone (the safe start waits)
    assert np.abs(s.samples["force_n"]).max() == 0.0
    report = verify(s)
    assert report["ok"], report
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    assert int((p.grid.density == 0).sum()) >= int((model.grid.density == 0).sum())
    assert not np.array_equal(p.grid.density, model.grid.density)


def test_devices_json_follows_the_stand_ins_plugged_and_unplugged(cfg_file, capsys,
                                                                  monkeypatch):
    """``bonesim devices --json`` over the hidapi stand-in (a SpaceMouse and a
    foot pedal) and pyusb's own find() over the ADU100 backend stand-in (as
    pyusb's libusb-1.0 backend): what is listed follows the plugs."""
    import usb.backend.libusb1 as libusb1

    from bonesim.cli.main import main
    from bonesim.devices.standins.adu100_usb import FakeADU100, FakeUsbBackend
    from bonesim.devices.standins.hid_bus import install

    bus = install(monkeypatch)
    box = FakeADU100()
    usb_backend = FakeUsbBackend(box)
    monkeypatch.setattr(libusb1, "get_backend", lambda *a, **k: usb_backend)

    def listing():
        assert main(["devices", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["config"] == str(cfg_file)
        return {b["name"]: b for b in out["backends"]}

    aux = ("spacemouse", "pedal", "adu100-handle")
    box.plugged = False
    out = listing()
    for name in aux:
        assert out[name]["library"] == "ok" and out[name]["connected"] == [], out[name]
    assert out["mouse"]["connected"] == ["always"]
    assert out["simulated-hand"]["connected"] == ["simulated hand"]
    bus.plug(b"/dev/hidraw3", 0x256F, 0xC635)                # SpaceMouse Compact
    bus.plug(b"/dev/hidraw5", 0x05F3, 0x00FF)                # Infinity IN-USB-2
    bus.plug(b"/dev/hidraw6", 0x046D, 0xC077)                # a mouse: no backend's
    box.plugged = True
    out = listing()
    assert out["spacemouse"]["connected"] == ["SpaceMouse Compact (256f:c635)"]
    assert out["pedal"]["connected"] == ["Infinity IN-USB-2 (05f3:00ff)"]
    assert out["adu100-handle"]["connected"] == ["ADU100 (bus 1 address 17)"]
    bus.unplug(b"/dev/hidraw3")
    box.plugged = False
    out = listing()
    assert out["spacemouse"]["connected"] == [] and out["adu100-handle"]["connected"] == []
    assert out["pedal"]["connected"] == ["Infinity IN-USB-2 (05f3:00ff)"]
