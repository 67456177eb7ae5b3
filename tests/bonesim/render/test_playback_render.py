"""Playback drawing offscreen: a frame at a given time (tool, HUD, surface,
camera, timeline pixels), keys and the timeline under the mouse, and a short
video export read back with imageio-ffmpeg."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.session.playback import Player
from bonesim.render.playback import (BAR_RGBA, CONTACT_RGBA, HEAD_RGBA, PLAYED_RGBA,
                                     PLAYBACK_KEYS, RESET_RGBA,
                                     PlaybackApp, PlaybackView, bar_rect, export_video)
from bonesim.render.scene import Scene
from tests.bonesim.session.test_playback import demo_file, fake_session  # noqa: F401 (fixture)

ROOT = Path(__file__).resolve().parents[3]

SIZE = (320, 240)


def view_bar(width, height):
    """The timeline bar of a window this size: it spans the 3D view, left of
    the side panel."""
    from bonesim.render.layout import panel_width_px
    from bonesim.render.style import default_style

    return bar_rect(width - panel_width_px(width, default_style().panel), height)


@pytest.fixture(scope="module")
def recorded():
    return fake_session()


@pytest.fixture
def view(gl_info, recorded):
    s, _ = recorded
    player = Player(s)
    scene = Scene.from_model(player.model, player.surface, size=SIZE, visible_subset=False)
    v = PlaybackView(scene, player, video=True)
    yield v
    scene.close()


def _key(win, sym):
    iren = win.interactor
    iren.SetEventInformation(10, 10, 0, 0, "\0", 0, sym)
    iren.InvokeEvent("KeyPressEvent")


def _mouse(win, event, x, y):
    iren = win.interactor
    iren.SetEventInformation(int(x), int(y), 0, 0, "\0", 0, None)
    iren.InvokeEvent(event)


def test_frame_at_a_time_places_tool_hud_surface_camera_and_bar(view, recorded):
    s, _ = recorded
    player, scene = view.player, view.scene
    t = 0.8
    f = view.show(t, speed=2.0)
    i = player.timeline.sample_index(t)
    assert i == 800
    # the tool at the recorded pose (burr placed by its user matrix)
    m = scene._burr.GetUserMatrix()
    assert [m.GetElement(r, 3) for r in range(3)] == pytest.approx(s.samples["pos_mm"][i])
    assert scene._burr.GetVisibility()
    # the HUD
    e, lo, hi = player.timeline.removal_range(t)
    hud = scene.hud_text
    assert "time: 0:00.8 / 0:01.8" in hud and "playback: 2x" in hud
    assert f"removed: {hi - lo:,} voxels" in hud and hi - lo > 50
    assert "injury 1 (Nerve)" in hud and "frame" not in hud    # no measured rate
    assert f"force  {np.linalg.norm(s.samples['force_n'][i]):.2f} N" in hud
    # the surface drawn is the player's, at that time
    assert scene.surface is player.surface
    assert scene._buffers.n_full == player.surface.n_triangles
    # the recorded camera, interpolated at t (eye moves 10 mm/s along x)
    assert scene.camera.GetPosition() == pytest.approx((16.0, 8.0, 60.0), abs=1e-6)
    # the timeline: played part left of the head, the rest right of it
    img = scene.image()
    x0, y0, x1, y1 = view_bar(*SIZE)
    xh = x0 + (x1 - x0) * t / player.timeline.duration
    row = SIZE[1] - 1 - (y0 + y1) // 2                   # image rows run top-down

    def near(px, rgba):
        want = np.array(rgba[:3], float) * rgba[3] / 255.0   # blended over a dark bg
        return np.abs(img[row, int(px)].astype(float) - want).max() < 40

    assert near(xh - 20, PLAYED_RGBA) and near(xh + 20, BAR_RGBA)
    assert any(near(xh + d, HEAD_RGBA) for d in (-1, 0, 1))
    # injury (contact: orange) and reset (white) ticks stick out above the bar
    tl = player.timeline
    above = SIZE[1] - 1 - (y1 + 1)
    for t_tick, rgba in ((tl.inj_t[0], CONTACT_RGBA), (tl.reset_t[0], RESET_RGBA)):
        xt = int(round(x0 + (x1 - x0) * t_tick / tl.duration))
        assert np.abs(img[above, xt].astype(int) - rgba[:3]).max() < 40, t_tick
    assert np.abs(img[above, (x0 + x1) // 2 + 7].astype(int) - CONTACT_RGBA[:3]).max() > 100
    # the HUD sits in the side panel, right of the bar
    assert scene.panel_rect()[0] >= x1


def test_backward_seek_redraws_a_rebuilt_surface(view):
    player, scene = view.player, view.scene
    view.show(1.1)
    big = scene._buffers.n_full
    surf = player.surface
    view.show(0.3)
    assert player.surface is not surf and scene.surface is player.surface
    assert scene._buffers.n_full == player.surface.n_triangles != big
    view.show(1.7)                                       # after the reset
    assert "since reset 1" in scene.hud_text and "injury none" in scene.hud_text


def test_keys_and_camera_follow(gl_info, recorded):
    s, _ = recorded
    now = [0.0]
    app = PlaybackApp(Player(s), size=SIZE, offscreen=True, play=False,
                      clock=lambda: now[0])
    with app:
        win = app.window
        assert set(PLAYBACK_KEYS.values()) <= set(("play_pause", "speed_up", "speed_down",
                                                   "seek_back_1s", "seek_forward_1s",
                                                   "seek_back_10s", "seek_forward_10s",
                                                   "seek_start", "seek_end", "reset_view",
                                                   "screenshot", "help", "quit"))
        _key(win, "space")
        assert app.clock.playing
        _key(win, "plus")
        _key(win, "plus")
        assert app.clock.speed == 4.0
        _key(win, "minus")
        assert app.clock.speed == 2.0
        app.run(frames=1)
        now[0] = 0.25                                    # 0.25 s wall at 2x
        app.run(frames=1)
        assert app.clock.t == pytest.approx(0.5)
        assert "time: 0:00.5 / 0:01.8" in app.scene.hud_text
        _key(win, "Right")
        assert app.clock.t == pytest.approx(1.5)
        _key(win, "Left")
        _key(win, "Left")
        assert app.clock.t == pytest.approx(0.0)
        _key(win, "End")
        assert app.clock.t == pytest.approx(app.clock.duration)
        _key(win, "Home")
        _key(win, "Up")
        assert app.clock.t == pytest.approx(app.clock.duration)   # +10 s clamps
        _key(win, "Down")
        assert app.clock.t == 0.0
        # following the recorded camera until the user orbits, then "v" returns
        _key(win, "space")                               # pause
        app.clock.seek(0.5)
        app.run(frames=1)
        assert app.scene.camera.GetPosition()[0] == pytest.approx(13.0)
        app.scene.camera.Azimuth(30)
        moved = app.scene.camera.GetPosition()
        app.clock.seek(0.9)
        app.run(frames=1)
        assert not app.view.follow and app.scene.camera.GetPosition() == pytest.approx(moved)
        _key(win, "v")
        assert app.view.follow
        assert app.scene.camera.GetPosition() == pytest.approx((17.0, 8.0, 60.0), abs=1e-6)
        _key(win, "q")
        assert win._quit


def test_click_and_drag_on_the_timeline_seek(gl_info, recorded):
    s, _ = recorded
    app = PlaybackApp(Player(s), size=SIZE, offscreen=True, play=True, clock=lambda: 0.0)
    with app:
        win, bar = app.window, app.view.bar
        x0, y0, x1, y1 = bar.rect()
        ym = (y0 + y1) / 2
        _mouse(win, "LeftButtonPressEvent", x0 + 0.25 * (x1 - x0), ym)
        assert app.dragging
        assert app.clock.t == pytest.approx(0.25 * app.clock.duration, abs=0.01)
        _mouse(win, "MouseMoveEvent", x0 + 0.75 * (x1 - x0), ym + 40)   # drag off the bar
        assert app.clock.t == pytest.approx(0.75 * app.clock.duration, abs=0.01)
        _mouse(win, "LeftButtonReleaseEvent", x0 + 0.75 * (x1 - x0), ym + 40)
        assert not app.dragging
        app.run(frames=1)
        assert app.player.t == pytest.approx(0.75 * app.clock.duration, abs=0.01)
        t = app.clock.t
        _mouse(win, "LeftButtonPressEvent", SIZE[0] / 2, SIZE[1] / 2)    # not on the bar
        _mouse(win, "LeftButtonReleaseEvent", SIZE[0] / 2, SIZE[1] / 2)
        assert app.clock.t == t and not app.dragging


@pytest.mark.slow
def test_short_video_export_has_the_frames_and_size(gl_info, recorded, tmp_path):
    import imageio_ffmpeg

    s, _ = recorded
    out = tmp_path / "clip.mp4"
    err = io.StringIO()
    info = export_video(Player(s), out, fps=10, size=(160, 120), speed=1.0, start=0.2,
                        end=1.7, stream=err)
    assert info["frames"] == 15 and info["size"] == [160, 120]
    assert info["start_s"] == 0.2 and info["end_s"] == pytest.approx(1.6)
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    frames = [np.frombuffer(b, np.uint8).reshape(120, 160, 3) for b in reader]
    assert meta["size"] == (160, 120) and len(frames) == 15
    assert meta["fps"] == pytest.approx(10.0) and meta["codec"].startswith("h264")
    # the timeline's played part grows along the bottom row of the bar
    x0, y0, x1, y1 = view_bar(160, 120)
    row = 120 - 1 - (y0 + y1) // 2
    blue = [int((f[row, x0:x1, 2].astype(int) - f[row, x0:x1, 0] > 60).sum()) for f in frames]
    assert blue == sorted(blue) and blue[-1] > blue[0] + 0.6 * (x1 - x0)
    assert "100%" in err.getvalue() and "done in" in err.getvalue()


@pytest.mark.slow
def test_cli_video_export_of_a_recorded_file(gl_info, demo_file, tmp_path, capsys):
    import imageio_ffmpeg

    from bonesim.cli.main import main

    out = tmp_path / "demo.mp4"
    assert main(["playback", str(demo_file), "--video", str(out), "--size", "192x108",
                 "--fps", "12", "--start", "2", "--end", "4", "--speed", "2",
                 "--json"]) == 0
    cap = capsys.readouterr()
    info = json.loads(cap.out)
    assert info["frames"] == 12 and info["size"] == [192, 108]
    assert "100%" in cap.err and "ETA" in cap.err
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert meta["size"] == (192, 108) and sum(1 for _ in reader) == 12


@pytest.mark.slow
def test_playback_window_under_xvfb(xdisplay, demo_file, tmp_path):
    """The real window (GLX on a virtual X server) plays, and its screenshot
    shows the timeline's played part."""
    shot = tmp_path / "win.png"
    env = dict(os.environ, DISPLAY=xdisplay, PYTHONPATH=str(ROOT))
    env.pop("BONESIM_GL", None)
    res = subprocess.run([sys.executable, "-m", "bonesim.cli", "playback", str(demo_file),
                          "--size", "320x240", "--start", "2", "--speed", "2", "--frames",
                          "30", "--screenshot", str(shot), "--json"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
    # it played on from the start (how far in 30 frames is a speed: the machine's)
    assert out["frames"] == 30 and 2.0 < out["t_s"] <= out["duration_s"] and out["playing"]
    assert "playback: 2x  playing" in out["hud"]
    from bonesim.render.imagecmp import read_png

    img = read_png(shot)
    x0, y0, x1, y1 = view_bar(320, 240)
    row = img.shape[0] - 1 - (y0 + y1) // 2
    xh = x0 + (x1 - x0) * out["t_s"] / out["duration_s"]
    played = img[row, x0 + 2:int(xh) - 3, :3].astype(int)
    assert (played[:, 2] - played[:, 0] > 60).all()        # blue left of the head
    rest = img[row, int(xh) + 4:x1 - 2, :3].astype(int)
    assert (np.abs(rest[:, 2] - rest[:, 0]) < 30).all()    # grey right of it
