"""The interactive app: offscreen, under Xvfb with its real timer loop, and
without a display or an audio device."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory
from bonesim.io.trajectory import write_trajectory

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def script(tmp_path_factory):
    """A few seconds of the demo path, from where it starts drilling bone."""
    traj = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:start + 500])
    path = tmp_path_factory.mktemp("app") / "script.csv"
    write_trajectory(path, traj)
    return traj, path


def _bonesim(args, env_update=None, drop=(), timeout=240):
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(env_update or {})
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "bonesim.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_offscreen_app_drills_updates_mesh_and_reports_rates(script, tmp_path):
    from bonesim.apps.simulator import App

    from bonesim.physics.force_limits import ForceLimits, ForceWatch, bin_edges, save_limits

    traj, _ = script
    e = bin_edges()                   # a force limit of 0.5 N at every distance
    save_limits(tmp_path / "lim.toml", ForceLimits(e, np.full(len(e) - 1, 0.5),
                                                   np.full(len(e) - 1, np.nan),
                                                   np.full(len(e) - 1, 9), 95.0,
                                                   "chorda_tympani", "applied", 30.0))
    app = App("phantom", "cutting-5mm", script=traj, offscreen=True, size=(320, 240),
              sound=False, record=tmp_path / "app.h5", who={"participant": "t1"},
              stereo="anaglyph", eye_separation_mm=60.0, force_limits=tmp_path / "lim.toml")
    try:
        app.start()
        assert app.scene.stereo_mode == "anaglyph" and app.scene.eye_separation_mm == 60.0
        before = app.consumer.surface.canonical()
        out = app.run(frames=90, screenshot=tmp_path / "shot.png")
        hud = app.scene.hud_text
        assert re.search(r"depth\s+(in view|\d+\.\d mm under bone)", hud), hud
        # the HUD shows the warning while it is recent, else the count (a
        # loaded machine may end the 90 frames after the burr stopped cutting)
        assert re.search(r"LIMIT! \d\.\d\d > 0\.50 N\n  \d+\.\d mm from Chorda tympani|"
                         r"limit  Chorda tympani: [\d,]+ over", hud), hud
        live = dict(app.watch.count)
        app.window.press("irrigation")                # w: the water wets the dust
        app.window.run_offscreen(10, realtime=True)
        assert app.irrigation and "water  on" in app.scene.hud_text
        assert app.dust.wetted_cells > 0
        dust = app.dust.total_cells
        bone = app.consumer.grid.density.sum(dtype=np.float64)
        updates = len(app.consumer.update_s)
        changed = app.consumer.surface.canonical().differences(before)
        trace_text = app.trace.text()                 # the nerve monitor's trace
        app.window.press("nerve_monitor")             # m hides it
        trace_hidden = not app.trace.visible and app.trace.text() == ""
        # reset the case: the loop restores the bone, the app rebuilds its side
        epoch = app.consumer.epoch
        app.window.press("reset_case")
        app.window.run_offscreen(10, realtime=True)
        assert app.consumer.epoch != epoch and not app.injuries
        assert app.consumer.grid.density.sum(dtype=np.float64) > bone
    finally:
        app.close()
    assert out["frames"] == 90 and out["voxels_removed"] > 0
    # the drawn mesh followed the drilling
    assert updates > 0 and changed
    assert out["haptic_rate_hz"] > 0 and "haptic" in hud and "frame" in hud
    assert dust > 0                                   # removed bone became dust
    # the nerve monitor ran on the loop's samples and its trace was drawn
    m = out["monitor"]
    assert m["nerves"] == ["facial_nerve", "chorda_tympani"] and m["source"] == "samples"
    assert m["updates"] > 100 and m["update_hz"] > 0  # (its rate is a figure: load-bound)
    assert "Facial nerve" in trace_text and "Chorda tympani" in trace_text and trace_hidden
    assert (tmp_path / "shot.png").stat().st_size > 1000
    # the session was recorded: samples, every removal, camera per frame, the key
    from bonesim.session.reader import read_session

    s = read_session(out["record"])
    assert s.complete and s.header["participant"] == "t1"
    assert len(s.camera["t_s"]) == 110 and ("key", "reset_case") in [e[1:] for e in s.events]
    assert s.samples["epoch"][-1] == 1 and len(s.removals["t_s"]) >= out["voxels_removed"]
    assert set(np.unique(s.removals["visible"])) <= {0, 1}     # judged from the camera
    # the live warnings are the recording's, up to the frame the window last read
    again = ForceWatch(app.model, app.watch.limits)
    again.feed(s.tissue, s.samples)
    again.feed()
    assert 0 < live["force_n"] <= again.count["force_n"] and live["speed_rpm"] == 0
    # the fragment finder ran behind the loop (on by default); whatever it
    # split or shed replays bit for bit
    assert out["fragments"]["rounds"] > 0 and app.fragments is None
    from bonesim.session.replay import verify

    assert verify(s)["ok"]


def test_window_timer_loop_under_xvfb(xdisplay, script, tmp_path):
    _, path = script
    res = _bonesim(["run", "--script", str(path), "--frames", "60", "--no-sound",
                    "--size", "320", "240", "--record", "--json"],
                   env_update={"DISPLAY": xdisplay})
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["frames"] == 60 and out["voxels_removed"] > 0
    assert out["haptic_rate_hz"] > 0        # the rate under load: the bench's figures
    assert out["surface_updates"] > 0                 # the mesh followed the drilling
    assert re.search(r"haptic\s+\d+ Hz\s+frame\s+\d+ Hz", out["hud"]), out["hud"]
    assert "no display" not in res.stderr             # it really used the X server
    # the window's run ends with the final product's checklist
    a = out["assessment"]
    assert a["checklist"][0].startswith(f"final product: {a['total']} of {a['max_total']}")
    assert {i["name"] for i in a["items"]} >= {"antrum", "sigmoid_sinus", "facial_nerve"}
    from bonesim.session.reader import read_session

    s = read_session(out["record"])                  # --record: the sessions folder
    assert Path(out["record"]).parent == Path(os.environ["BONESIM_SESSIONS"])
    assert s.complete and len(s.camera["t_s"]) == 60


def test_no_display_and_no_audio_fall_back_with_clear_messages(tmp_path):
    wav = tmp_path / "drill.wav"
    res = _bonesim(["run", "--frames", "20", "--size", "320", "240", "--wav", str(wav),
                    "--screenshot", str(tmp_path / "x.png"), "--json"],
                   drop=("DISPLAY", "WAYLAND_DISPLAY"))
    assert res.returncode == 0, res.stderr
    assert "no display found" in res.stderr
    out = json.loads(res.stdout)
    # one notice, in the run's notes (the HUD and the summary), not also on stderr
    assert "no audio" not in res.stderr
    assert [n for n in out["notices"] if "no audio device" in n] == [
        f"no audio device: sound muted, recorded to {wav}"]
    assert out["frames"] == 20 and Path(out["screenshot"]).is_file()
    assert wav.is_file() and wav.stat().st_size > 1000


def test_the_hud_shows_the_pedal_state_and_a_handles_angles():
    """What the window adds to its HUD from the loop's status for a pedal
    or an instrumented handle (``status["pedal"]``, ``status["handle_deg"]``)."""
    from types import SimpleNamespace

    from bonesim.apps.simulator import App
    from bonesim.runtime.haptic_loop import STATUS

    status = np.zeros((), [f[:2] if len(f) == 2 else (f[0], f[1], f[2]) for f in STATUS])
    status["pedal"] = 1
    status["handle_deg"] = np.nan
    app = SimpleNamespace(loop=SimpleNamespace(pedal=object(), status=status), recorder=None)
    assert App._pedal_status(app) == {}                 # a foot pedal: no angles
    status["handle_deg"][:2] = (7.5, 90.0)
    assert App._pedal_status(app) == {"handle": "7.5 / 90.0 deg"}
    status["pedal"] = 2
    assert App._pedal_status(app) == {"pedal": "UNPLUGGED - drill off"}   # not stale ones
    app.loop.pedal = None
    assert App._pedal_status(app) == {}


# Issue 24, row 6: a limits file naming a structure the case lacks.
def test_a_structure_the_case_lacks_is_one_line_not_an_unbound_error(tmp_path):
    """The simulator's check of --force-limits (it raised UnboundLocalError:
    a local import shadowed BonesimError in App.__init__)."""
    from types import SimpleNamespace

    from bonesim.apps.simulator import App
    from bonesim.errors import BonesimError
    from bonesim.io.loading import load_model

    p = tmp_path / "lim.toml"
    p.write_text("format = 'bonesim-force-limits-1'\nstructure = 'no_such_nerve'\n"
                 "force = 'applied'\npercentile = 95.0\nmax_distance_mm = 4.0\n"
                 "edges_mm = [0.0, 2.0, 4.0]\nforce_n = [1.0, 2.0]\nspeed_rpm = [1.0, 2.0]\n"
                 "n = [1, 1]\n")
    fake = SimpleNamespace(model=load_model("phantom", "cutting-5mm"), want_monitor=True,
                           notices=[])
    with pytest.raises(BonesimError, match=r"lim.toml \[structure\]: .*'no_such_nerve' is "
                                           r"not a structure of case 'phantom'"):
        App._checked_options(fake, None, p)
    fake.want_monitor = False
    with pytest.raises(BonesimError, match=r"\[--monitor-port\]: case 'phantom' monitors no"):
        App._checked_options(fake, {"port": 0}, None)
