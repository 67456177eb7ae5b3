"""Tutoring with real device backends: the Touch stand-in (the HD library
stub, compiled by the test) as the instructor's hand in the haptic loop's
process and as the trainee's driven device in this one, over loopback;
both device records kept; the ideal follower beside it; one-line device
errors."""
from __future__ import annotations

import ctypes
import os
from pathlib import Path

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.tutoring import server as tutor_server
from bonesim.tutoring import servo as tutor_servo
from bonesim.tutoring import sources as tutor_sources
from tests.bonesim.session.test_playback import demo_file  # noqa: F401 (fixture)
from tests.bonesim.waiting import wait_until

KEY = bytes(range(32))
STUB_OWN = (0.88, 160.0, 120.0, 70.0, 0.39)          # hd_stub.c's record


def _caps(rec: dict) -> tuple:
    c = rec["caps"]
    return (c["max_force_n"], *c["workspace_mm"], c["max_stiffness_n_per_mm"])


@pytest.fixture(scope="module")
def stub():
    from bonesim.devices.standins.hd_library import load

    return load()


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_touch_on_both_ends_over_loopback_records_both_devices(stub, tmp_path, monkeypatch):
    from bonesim.devices.config import CONFIG_ENV
    from bonesim.devices.safety import ACTIVE, RAMPING
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header
    from bonesim.session.reader import read_session
    from bonesim.tutoring.devices import instructor_backend, trainee_device

    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "devices.toml"))
    folder = str(Path(stub._name).parent)               # the loop's process finds it here
    monkeypatch.setenv("LD_LIBRARY_PATH",
                       folder + os.pathsep + os.environ.get("LD_LIBRARY_PATH", ""))
    case = load_case("phantom")
    backend, irec = instructor_backend("touch", case)    # probed: the stub's own record
    assert irec["backend"] == "touch" and _caps(irec) == pytest.approx(STUB_OWN)
    model = load_model("phantom", "cutting-5mm", device=backend.caps)
    path = tmp_path / "instructor.h5"
    loop = HapticLoop(model, device=("device", backend), vibration=False)
    rec = Recorder(loop, path, make_header(model, input_device="touch", device_record=irec))
    trainee = None
    try:
        rec.start()
        loop.start()
        server = tutor_server.TutorServer(loop, KEY, host="127.0.0.1", port=0).start()
        try:
            src = tutor_sources.NetworkSource("127.0.0.1", server.port, KEY, model=model)
            src.connect(30.0)
            # the trainee's stylus rests 1 mm off the instructor's tool (device x)
            stub.stub_place(1.0, 0.0, 0.0)
            dev, trec = trainee_device("touch", src.state.pos_mm.copy(), case)
            trainee = tutor_servo.Trainee(src, dev)
            assert wait_until(lambda: dev.device.ticks > 20)     # the arm's servo runs
            start_err = float(np.linalg.norm(dev.read(0.0).pos_mm - src.state.pos_mm))
            trainee.run(3.0)
            stats = trainee.stats()
            events = dev.take_events()
            pos = (ctypes.c_double * 3)()
            stub.stub_position(pos)
        finally:
            if trainee is not None:
                trainee.close()
                trainee.device.close()
            final = server.close()
        loop.stop()
        rec.close()
    finally:
        loop.close()
    # the trainee's Touch: its own record, behind the safety layer, driven
    assert trec["backend"] == "touch" and _caps(trec) == pytest.approx(STUB_OWN)
    assert trainee.max_force_n == pytest.approx(0.88)
    assert dev.state in (ACTIVE, RAMPING) and dev.unplugs == 0, stats["device"]
    assert stats["force_n"]["max"] <= 0.88 + 1e-9
    assert start_err == pytest.approx(1.0, abs=0.05)
    assert pos[0] < 0.9, (list(pos), events, stats)   # the law pulled the stylus to the tool
    # (counts loose: two cores shared by the loop, the server and this servo)
    assert stats["packets"]["accepted"] > 100 and final["sent"] > 100
    v = stats["tracking_vs_ideal"]
    lt = v["law_target"]
    assert lt["session"]["n"] > 100 and lt["session"]["n"] == lt["ideal"]["n"]
    # the ideal follower (no link, no join ramp, no arm) follows the law at least as well
    assert lt["ideal"]["mean"] <= lt["session"]["mean"], v
    # the instructor's Touch: its record in its session header
    s = read_session(path)
    assert s.header["device_record"]["backend"] == "touch"
    assert _caps(s.header["device_record"]) == pytest.approx(STUB_OWN)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_demo_motion_on_the_touch_over_loopback_follows_no_better_than_the_ideal(
        stub, tmp_path, monkeypatch):
    """The built-in demo motion (the bench's set-up) to a trainee's Touch
    stand-in over loopback: the ideal follower, scored at the same instants,
    follows the law at least as well, and what limits the session is named."""
    from bonesim.devices.config import CONFIG_ENV
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.tutoring.devices import trainee_device
    from bonesim.tutoring.ideal import HANDICAPS

    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "devices.toml"))
    model = load_model("phantom", "cutting-5mm")
    traj = demo_trajectory(model.case, "cutting-5mm")
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:])
    loop = HapticLoop(model, device=("scripted", traj), vibration=False, run_s=60.0)
    trainee = None
    try:
        loop.start()
        server = tutor_server.TutorServer(loop, KEY, host="127.0.0.1", port=0).start()
        try:
            src = tutor_sources.NetworkSource("127.0.0.1", server.port, KEY, model=model)
            src.connect(30.0)
            stub.stub_place(0.0, 0.0, 0.0)
            dev, trec = trainee_device("touch", src.state.pos_mm.copy(), model.case)
            trainee = tutor_servo.Trainee(src, dev)
            trainee.run(3.0)
            stats = trainee.stats()
        finally:
            if trainee is not None:
                trainee.close()
                trainee.device.close()
            server.close()
    finally:
        loop.close()
    assert trec["backend"] == "touch"
    v = stats["tracking_vs_ideal"]
    lt = v["law_target"]
    # (how many ticks were scored depends on the load: the link counts as lost after 20 ms)
    assert lt["session"]["n"] == lt["ideal"]["n"] > 0, (v, stats.get("packets"))
    assert v["span_s"][1] - v["span_s"][0] == pytest.approx(v["seconds"], abs=1e-3)
    assert v["value"] >= 1.0, v
    worst = v["limited_by"]
    assert worst in HANDICAPS and v["handicaps"][worst] >= lt["ideal"]["mean"]


def test_device_names_and_kinds_are_refused_in_one_line(tmp_path, monkeypatch, capsys):
    from bonesim.cli.main import main
    from bonesim.net import packets as net

    key = net.write_key(tmp_path / "k")
    for argv, want in ((["tutor", "join", "127.0.0.1", "--device", "nope"], "unknown device"),
                       (["tutor", "join", "127.0.0.1", "--device", "spacemouse"],
                        "renders no force"),
                       (["tutor", "join", "127.0.0.1", "--device", "mouse"],
                        "renders no force"),
                       (["tutor", "playback", "x.h5", "--device", "pedal"],
                        "renders no force"),
                       (["tutor", "serve", "--headless", "--device", "nope"],
                        "unknown device"),
                       (["tutor", "serve", "--headless", "--device", "mouse"],
                        "mouse drives the tool only in the window")):
        rc = main(argv + ["--key-file", str(key)] if argv[1] != "playback" else argv)
        err = capsys.readouterr().err
        assert rc == 2 and want in err and err.count("\n") == 1, (argv, err)
        assert "--device" in err and "Traceback" not in err


# ------------------------------------------------------------------- CLI
@pytest.mark.slow
def test_cli_serve_with_a_device_records_its_record_in_the_header(tmp_path, capsys,
                                                                  monkeypatch):
    import json

    from bonesim.cli.main import main
    from bonesim.devices.config import CONFIG_ENV
    from bonesim.devices.simulated_hand import SIM_HAND_CAPS
    from bonesim.net import packets as net
    from bonesim.session.reader import read_session

    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "devices.toml"))
    key = net.write_key(tmp_path / "k")
    h5 = tmp_path / "instructor.h5"
    rc = main(["tutor", "serve", "--headless", "--device", "simulated-hand", "--duration",
               "1", "--host", "127.0.0.1", "--port", "0", "--key-file", str(key),
               "--record", str(h5), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)
    assert s["device_record"]["backend"] == "simulated-hand" and s["record"] == str(h5)
    assert s["device"]["state"] in ("waiting", "ramping", "active")
    head = read_session(h5).header
    assert head["device_record"]["backend"] == "simulated-hand"
    assert head["device_record"]["caps"]["max_force_n"] == SIM_HAND_CAPS.max_force_n
    assert head["input"] == "simulated-hand"


def test_bench_entries_registered_and_main_job_runs_only_when_named(monkeypatch):
    from bonesim.bench import suite

    assert "tutor_tracking_vs_ideal" in suite.BENCHMARKS
    assert "main_job_s" in suite.BENCHMARKS and "main_job_s" in suite.ON_REQUEST
    ran = []

    def fake(name):
        def run(quick=False):
            ran.append(name)
            return {name: {"value": 1.0, "unit": "x"}}
        return run

    monkeypatch.setattr(suite, "BENCHMARKS", {"a": fake("a"), "main_job_s": fake("main_job_s")})
    assert set(suite.run_benchmarks()) == {"a"} and ran == ["a"]
    assert set(suite.run_benchmarks(only=["main_job_s"])) == {"main_job_s"}


def test_summaries_explain_the_words_they_show_once():
    from bonesim.tutoring.ideal import tracking_vs_ideal

    from bonesim.cli.tutor import _glossary_lines, _trainee_lines
    from bonesim.net.tutor_protocol import GLOSSARY

    s = {"ticks": 10, "packets": {"accepted": 5, "stale": 3}, "link_lost_events": 1,
         "link_lost": True, "hud": "LINK LOST",
         "tracking_vs_ideal": {"tool": tracking_vs_ideal([9.0, 12.0], [10.0, 13.0]),
                               "law_target": tracking_vs_ideal([2.0, 3.0], [1.0, 2.0]),
                               "value": 1.667, "seconds": 2.0, "limited_by": "hand",
                               "handicaps": {"hand": 2.4, "link_delay": 1.6}}}
    lines = _trainee_lines(s)
    assert sum(GLOSSARY["stale"] in x for x in lines) == 1
    assert sum(GLOSSARY["link lost"] in x for x in lines) == 1
    assert any("ideal follower's 1.5 mm" in x and "ratio 1.667" in x for x in lines)
    assert any("limits it most" in x and "resistance" in x for x in lines)
    assert _glossary_lines({"go_backs": 2, "received": {"stale": 0}}, None) == \
        ["  " + GLOSSARY["go-back"]]
    assert _glossary_lines({"go_backs": 0, "received": {}}, {"packets": {}}) == []


def test_cli_playback_with_a_device_writes_the_trainees_record(demo_file, tmp_path, capsys,
                                                                monkeypatch):
    import json

    from bonesim.cli.main import main
    from bonesim.devices.config import CONFIG_ENV
    from bonesim.devices.simulated_hand import SIM_HAND_CAPS

    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "devices.toml"))
    out_json = tmp_path / "trainee.json"
    rc = main(["tutor", "playback", str(demo_file), "--headless", "--device",
               "simulated-hand", "--duration", "1.5", "--record", str(out_json), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)
    assert s["record"] == str(out_json) and s["device"]["state"] in ("ramping", "active")
    rec = json.loads(out_json.read_text())
    head = rec["header"]
    assert head["role"] == "trainee" and head["input"] == "simulated-hand"
    assert head["device_record"]["backend"] == "simulated-hand"
    assert head["device_record"]["caps"]["max_force_n"] == SIM_HAND_CAPS.max_force_n
    assert head["case"]["name"] and head["source"] == ["recording", str(demo_file)]
    assert rec["summary"]["tracking_vs_ideal"]["law_target"]["ideal"]["n"] > 0
