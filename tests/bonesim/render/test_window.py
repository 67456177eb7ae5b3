"""Window: offscreen frame loop, key actions, mouse for the tool, camera gestures.

Events are injected into the window's (display-less) interactor exactly as
an X server's would arrive."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.render.scene import Scene
from bonesim.render.window import (ACTIONS, DEFAULT_KEYS, LEFT, MOUSE_HELP, Window)


@pytest.fixture
def scene(gl_info):
    sc = Scene(size=(200, 150))
    sc.set_case_camera((0.0, 0.0, 100.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    sc.set_tool((0.0, 0.0, 5.0), (0, 0, -1), 1.0)
    yield sc
    sc.close()


class Recorder:
    def __init__(self, handled=()):
        self.keys, self.mouse, self.frames = [], [], 0
        self.handled = set(handled)

    def on_frame(self, scene):
        self.frames += 1

    def on_key(self, action):
        self.keys.append(action)
        return action in self.handled

    def on_mouse(self, p, buttons):
        self.mouse.append((np.array(p), buttons))


def make(scene, rec, **kw):
    return Window(scene, rec.on_frame, rec.on_key, rec.on_mouse, **kw)


def key(win, sym, ctrl=0, shift=0):
    iren = win.interactor
    iren.SetEventInformation(100, 75, ctrl, shift, "\0", 0, sym)
    iren.InvokeEvent("KeyPressEvent")
    iren.InvokeEvent("CharEvent")


def mouse(win, event, x, y, ctrl=0, shift=0):
    iren = win.interactor
    iren.SetEventInformation(x, y, ctrl, shift, "\0", 0, None)
    iren.InvokeEvent(event)


def test_offscreen_loop_calls_on_frame_and_saves_the_last_frame(scene, tmp_path):
    rec = Recorder()
    win = make(scene, rec)
    out = win.run_offscreen(5, screenshot=tmp_path / "last.png")
    assert rec.frames == 5 and win.frames == 5 and out["frames"] == 5
    assert (tmp_path / "last.png").stat().st_size > 0
    assert win.run(max_frames=2)["frames"] == 2          # run() on an offscreen scene


def test_default_keys_map_to_actions(scene):
    rec = Recorder()
    win = make(scene, rec)
    for sym in ("n", "p", "space", "r", "plus", "minus", "s", "BackSpace", "x", "Up", "Down"):
        key(win, sym)
    assert rec.keys == ["next_burr", "previous_burr", "drill_toggle", "reverse", "speed_up",
                        "speed_down", "suction", "reset_case", "reset_case", "depth_in",
                        "depth_out"]
    key(win, "N")                                         # shifted letters too
    key(win, "w")                                         # irrigation (not VTK's wireframe)
    key(win, "j")                                         # unmapped: nothing
    assert rec.keys[-2:] == ["next_burr", "irrigation"] and len(rec.keys) == 13
    assert scene.surface_actor.GetProperty().GetRepresentation() == 2   # still surface
    assert set(DEFAULT_KEYS.values()) <= set(ACTIONS)
    assert "h" in scene.help_actor.GetInput() or "help" in scene.help_actor.GetInput()


def test_window_defaults_and_handled_override(scene, tmp_path):
    rec = Recorder()
    win = make(scene, rec, screenshot_dir=tmp_path)
    key(win, "h")
    assert scene.help_actor.GetVisibility()
    key(win, "F12")
    assert len(win.screenshots) == 1 and win.screenshots[0].exists()
    scene.camera.Azimuth(40)
    key(win, "v")
    assert scene.camera.GetPosition() == pytest.approx((0, 0, 100))
    key(win, "q")
    assert rec.keys == ["help", "screenshot", "reset_view", "quit"] and win._quit
    # an app that handles "help" itself suppresses the default toggle
    rec2 = Recorder(handled={"help"})
    win2 = make(scene, rec2)
    vis = scene.help_actor.GetVisibility()
    key(win2, "F1")
    assert scene.help_actor.GetVisibility() == vis and rec2.keys == ["help"]
    with pytest.raises(ValueError):
        win2.press("explode")
    with pytest.raises(ValueError):
        Window(scene, keys={"k": "explode"})


def test_quit_stops_the_offscreen_loop(scene):
    rec = Recorder()
    win = make(scene, rec)
    rec.on_frame = lambda sc: win.press("quit") if win.frames == 2 else None
    win.on_frame = rec.on_frame
    assert win.run_offscreen(50)["frames"] == 3


def test_mouse_moves_the_tool_in_the_view_plane(scene):
    rec = Recorder()
    win = make(scene, rec)
    scene.render()
    x0, y0, x1, y1 = scene.view_rect()              # the 3D view, left of the panel
    cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
    mouse(win, "MouseMoveEvent", cx, cy)
    p, b = rec.mouse[-1]
    assert b == 0 and p == pytest.approx((0, 0, 5.0), abs=0.5)
    mouse(win, "LeftButtonPressEvent", x1 - 15, cy)
    mouse(win, "MouseMoveEvent", x1 - 5, cy)
    p, b = rec.mouse[-1]
    assert b == LEFT and p[2] == pytest.approx(5.0) and p[0] > 3.0     # right of centre
    mouse(win, "LeftButtonReleaseEvent", x1 - 5, cy)
    assert rec.mouse[-1][1] == 0


def test_camera_gestures_do_not_move_the_tool(scene):
    rec = Recorder()
    win = make(scene, rec)
    scene.render()
    cam = scene.camera
    start = cam.GetPosition()
    mouse(win, "RightButtonPressEvent", 100, 75)       # right drag: orbit
    mouse(win, "MouseMoveEvent", 140, 75)
    mouse(win, "RightButtonReleaseEvent", 140, 75)
    assert rec.mouse == []
    assert np.linalg.norm(np.subtract(cam.GetPosition(), start)) > 5.0
    assert np.linalg.norm(cam.GetPosition()) == pytest.approx(100.0, rel=1e-3)
    scene.reset_camera()
    mouse(win, "LeftButtonPressEvent", 100, 75, ctrl=1, shift=1)   # Ctrl+Shift+left: pan
    mouse(win, "MouseMoveEvent", 120, 75, ctrl=1, shift=1)
    mouse(win, "LeftButtonReleaseEvent", 120, 75, ctrl=1, shift=1)
    assert rec.mouse == [] and cam.GetFocalPoint()[0] < -1.0
    scene.reset_camera()
    mouse(win, "MouseWheelForwardEvent", 100, 75, ctrl=1)          # Ctrl+wheel: zoom
    assert np.linalg.norm(cam.GetPosition()) < 99.0
    mouse(win, "MouseWheelForwardEvent", 100, 75)                  # wheel: tool depth
    mouse(win, "MouseWheelBackwardEvent", 100, 75)
    assert rec.keys == ["depth_in", "depth_out"]


def test_callback_errors_end_the_loop_and_propagate(scene):
    def boom(sc):
        raise RuntimeError("app failed")

    win = Window(scene, boom)
    with pytest.raises(RuntimeError, match="app failed"):
        win.run_offscreen(10)
    assert win.frames == 1


def test_mouse_help_text():
    assert any("orbit" in ln for ln in MOUSE_HELP) and any("depth" in ln for ln in MOUSE_HELP)
