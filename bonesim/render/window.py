"""The interactive window: a frame loop around a :class:`~bonesim.render.scene.Scene`,
keys mapped to named actions, and the mouse driving the tool.

The app provides three callables; the window calls them on the rendering
(main) thread:

``on_frame(scene) -> None``
    Once per frame before the scene renders, from a repeating VTK timer at
    ``frame_hz`` (interactive) or from a plain loop (offscreen). Pull the
    haptic side's data here: drain the removal rings, ``Surface.update``,
    :meth:`Scene.update_surface`, :meth:`Scene.set_tool`,
    :meth:`Scene.set_dust`, :meth:`Scene.set_hud`.
``on_key(action) -> bool | None``
    A named action (see :data:`ACTIONS`) from a key, the wheel, or
    :meth:`Window.press`. Return True to say "handled": the window then
    skips its own default for that action. Defaults exist for ``help``
    (toggle the overlay), ``screenshot`` (PNG into ``screenshot_dir``),
    ``reset_view`` (case camera) and ``quit`` (end the loop); every other
    action is the app's to implement.
``on_mouse(world_mm, buttons) -> None``
    The mouse moved (or a tool button changed) while no camera gesture is
    in progress. ``world_mm`` (3,) float64 is the point under the cursor on
    the plane through the tool (the last :meth:`Scene.set_tool` position,
    else the focal point) perpendicular to the view direction [mm];
    ``buttons`` is a bit mask of :data:`LEFT`, :data:`MIDDLE`, :data:`RIGHT`
    held for the tool (left only: the others belong to the camera).

Mouse (microscope camera, trackball style)
------------------------------------------
========================  =============================================
move / left drag          tool follows the cursor in the view plane
wheel                     ``depth_in`` / ``depth_out`` actions (tool depth)
right drag                orbit the camera about the focal point
Shift + right, middle     pan
Ctrl + right drag         zoom (dolly)
Ctrl + left drag          orbit;  Ctrl + Shift + left: pan
Ctrl + wheel              zoom
========================  =============================================

A window without ``on_mouse`` drives no tool (a viewer): there a left drag
orbits (Shift + left pans) and the wheel zooms.

Default keys: :data:`DEFAULT_KEYS` (shown by the help overlay, ``h``).
"""
from __future__ import annotations

import time
from pathlib import Path


from vtkmodules.vtkInteractionStyle import vtkInteractorStyleTrackballCamera
from vtkmodules.vtkRenderingCore import vtkRenderWindowInteractor
from vtkmodules.vtkRenderingUI import vtkGenericRenderWindowInteractor

from bonesim.render.hud import format_help

__all__ = ["LEFT", "MIDDLE", "RIGHT", "ACTIONS", "DEFAULT_KEYS", "MOUSE_HELP", "Window"]

#: Button bits of ``on_mouse``'s ``buttons``.
LEFT, MIDDLE, RIGHT = 1, 2, 4

#: Every action a key or the wheel can produce.
ACTIONS = ("next_burr", "previous_burr", "drill_toggle", "reverse", "speed_up",
           "speed_down", "suction", "irrigation", "reset_case", "screenshot", "help", "quit",
           "depth_in", "depth_out", "reset_view", "nerve_monitor", "cut_plane", "cut_stroke",
           # session playback (bonesim.render.playback)
           "play_pause", "seek_back_1s", "seek_forward_1s", "seek_back_10s",
           "seek_forward_10s", "seek_start", "seek_end",
           # fragments and plates (bonesim.runtime.rigid_commands)
           "grab_toggle", "place_plate", "affix_plate", "distract_more", "distract_less")

#: Default key map: VTK key symbol -> action.
DEFAULT_KEYS = {
    "n": "next_burr", "p": "previous_burr",
    "space": "drill_toggle",
    "r": "reverse",
    "plus": "speed_up", "equal": "speed_up", "KP_Add": "speed_up",
    "minus": "speed_down", "KP_Subtract": "speed_down",
    "s": "suction",
    "w": "irrigation",
    "BackSpace": "reset_case", "x": "reset_case",
    "F12": "screenshot", "c": "screenshot",
    "h": "help", "F1": "help",
    "Up": "depth_in", "Down": "depth_out",
    "v": "reset_view", "Home": "reset_view",
    "m": "nerve_monitor",
    "k": "cut_plane", "Return": "cut_stroke",
    "q": "quit", "Escape": "quit",
    "g": "grab_toggle", "b": "place_plate", "a": "affix_plate",
    "bracketright": "distract_more", "bracketleft": "distract_less",
}

MOUSE_HELP = (
    "move / left drag   tool in the view plane",
    "wheel, Up/Down     tool depth",
    "right drag         orbit camera     Ctrl+left drag: orbit",
    "Shift+right, mid   pan              Ctrl+Shift+left: pan",
    "Ctrl+right, Ctrl+wheel  zoom",
)

# vtkInteractorStyle states
_NONE, _ROTATE, _PAN, _SPIN, _DOLLY = 0, 1, 2, 3, 4


class Window:
    """Frame loop, keys and mouse around a scene.

    Parameters
    ----------
    scene : Scene
        Made with ``offscreen=False`` for an interactive window (needs an X
        display, e.g. Xvfb); an offscreen scene runs :meth:`run_offscreen`.
    on_frame, on_key, on_mouse : callable, optional
        See the module docstring.
    frame_hz : float
        Target frame rate [Hz] (timer period ``1000 / frame_hz`` ms).
    keys : dict, optional
        Key symbol -> action (default :data:`DEFAULT_KEYS`).
    screenshot_dir : path
        Where the default ``screenshot`` action writes.

    Attributes
    ----------
    frames : int
        Frames drawn by the loop.
    interactor : vtkRenderWindowInteractor
        The event source (a generic, display-less one for offscreen scenes,
        so events can still be injected in tests).
    """

    def __init__(self, scene, on_frame=None, on_key=None, on_mouse=None, *,
                 frame_hz: float = 60.0, keys: dict | None = None,
                 screenshot_dir="."):
        if not frame_hz > 0:
            raise ValueError(f"frame_hz must be positive, got {frame_hz}")
        self.scene = scene
        self.on_frame = on_frame
        self.on_key = on_key
        self.on_mouse = on_mouse
        self.frame_hz = float(frame_hz)
        self.keys = dict(DEFAULT_KEYS if keys is None else keys)
        bad = sorted(set(self.keys.values()) - set(ACTIONS))
        if bad:
            raise ValueError(f"unknown action(s) in key map: {bad}; known: {list(ACTIONS)}")
        self.screenshot_dir = Path(screenshot_dir)
        self.frames = 0
        self.buttons = 0
        self.screenshots: list = []
        self._quit = False
        self._error = None
        self._max_frames = None
        self._timer = None
        self._shot_n = 0
        scene.set_help(format_help(self.keys, MOUSE_HELP))
        rw = scene.render_window
        if scene.offscreen:
            iren = vtkGenericRenderWindowInteractor()
        else:
            iren = vtkRenderWindowInteractor()
        iren.SetRenderWindow(rw)
        style = vtkInteractorStyleTrackballCamera()
        iren.SetInteractorStyle(style)
        self.interactor = iren
        self.style = style
        for ev, fn in (("MouseMoveEvent", self._move),
                       ("LeftButtonPressEvent", self._left_down),
                       ("LeftButtonReleaseEvent", self._left_up),
                       ("RightButtonPressEvent", self._right_down),
                       ("RightButtonReleaseEvent", self._button_up),
                       ("MiddleButtonPressEvent", self._middle_down),
                       ("MiddleButtonReleaseEvent", self._button_up),
                       ("MouseWheelForwardEvent", self._wheel_fwd),
                       ("MouseWheelBackwardEvent", self._wheel_back),
                       ("KeyPressEvent", self._key),
                       ("CharEvent", self._swallow),
                       ("KeyReleaseEvent", self._swallow)):
            style.AddObserver(ev, fn)
        iren.AddObserver("TimerEvent", self._tick)
        iren.AddObserver("ExitEvent", self._exit_event)

    # -------------------------------------------------------------- actions
    def press(self, action: str) -> None:
        """Fire ``action`` as if its key were pressed."""
        if action not in ACTIONS:
            raise ValueError(f"unknown action {action!r}; known: {list(ACTIONS)}")
        handled = False
        if self.on_key is not None:
            handled = bool(self._guard(self.on_key, action))
        if handled:
            return
        sc = self.scene
        if action == "help":
            sc.show_help()
            self._render_now()
        elif action == "screenshot":
            self.screenshot_dir.mkdir(parents=True, exist_ok=True)
            self._shot_n += 1
            stamp = time.strftime("%Y%m%d-%H%M%S")
            path = self.screenshot_dir / f"bonesim-{stamp}-{self._shot_n:03d}.png"
            self.screenshots.append(sc.screenshot(path))
        elif action == "reset_view":
            sc.reset_camera()
            self._render_now()
        elif action == "quit":
            self.quit()

    def quit(self) -> None:
        """End the loop after the current frame."""
        self._quit = True
        if not self.scene.offscreen:
            self.interactor.TerminateApp()

    # ------------------------------------------------------------------ loop
    def run(self, max_frames: int | None = None) -> dict:
        """Show the window and run the frame loop until ``quit`` (or
        ``max_frames`` frames). Offscreen scenes run :meth:`run_offscreen`.

        Returns
        -------
        dict
            ``frames``, ``seconds``, ``frame_hz`` (mean over the run).
        """
        if self.scene.offscreen:
            return self.run_offscreen(max_frames if max_frames is not None else 1)
        self._quit = False
        self._max_frames = max_frames
        iren = self.interactor
        t0 = time.perf_counter()
        f0 = self.frames
        iren.Initialize()
        self.scene.render()
        self._timer = iren.CreateRepeatingTimer(max(1, int(round(1000.0 / self.frame_hz))))
        try:
            if not self._quit:
                iren.Start()
        finally:
            if self._timer is not None:
                iren.DestroyTimer(self._timer)
                self._timer = None
        if self._error is not None:
            err, self._error = self._error, None
            raise err
        return self._summary(t0, f0)

    def run_offscreen(self, n_frames: int, screenshot=None, realtime: bool = False) -> dict:
        """Draw ``n_frames`` frames through the same ``on_frame`` callback,
        with no display, and optionally save the last one.

        Parameters
        ----------
        n_frames : int
        screenshot : path, optional
            PNG written after the last frame.
        realtime : bool
            Pace the frames at ``frame_hz`` (sleep) instead of as fast as
            possible.
        """
        self._quit = False
        period = 1.0 / self.frame_hz
        t0 = time.perf_counter()
        f0 = self.frames
        for _ in range(int(n_frames)):
            ts = time.perf_counter()
            self._frame()
            if self._error is not None:
                err, self._error = self._error, None
                raise err
            if self._quit:
                break
            if realtime:
                left = period - (time.perf_counter() - ts)
                if left > 0:
                    time.sleep(left)
        out = self._summary(t0, f0)
        if screenshot is not None:
            out["screenshot"] = str(self.scene.screenshot(screenshot))
        return out

    def _summary(self, t0, f0) -> dict:
        dt = time.perf_counter() - t0
        n = self.frames - f0
        return {"frames": n, "seconds": round(dt, 4),
                "frame_hz": round(n / dt, 2) if dt > 0 else 0.0}

    def _frame(self):
        if self.on_frame is not None:
            self._guard(self.on_frame, self.scene)
        self.scene.render()
        self.frames += 1

    def _tick(self, *_):
        if self._quit:
            return
        self._frame()
        if self._error is not None or (self._max_frames is not None
                                       and self.frames >= self._max_frames):
            self.quit()

    def _guard(self, fn, *args):
        """Call an app callback; an exception stops the loop and is re-raised
        by :meth:`run` (VTK would otherwise print and swallow it)."""
        try:
            return fn(*args)
        except Exception as exc:   # noqa: BLE001 - re-raised after the loop
            if self._error is None:
                self._error = exc
            self._quit = True
            if not self.scene.offscreen:
                self.interactor.TerminateApp()
            return None

    def _render_now(self):
        if not self.scene.offscreen:
            self.scene.render()

    def _exit_event(self, *_):
        self.press("quit")
        self.quit()

    # ----------------------------------------------------------------- mouse
    def _world(self):
        x, y = self.interactor.GetEventPosition()
        return self.scene.display_to_plane(x, y)

    def _report_mouse(self):
        if self.on_mouse is not None:
            self._guard(self.on_mouse, self._world(), self.buttons)

    def _camera_busy(self) -> bool:
        return self.style.GetState() != _NONE

    def _start(self, state):
        st = self.style
        x, y = self.interactor.GetEventPosition()
        st.FindPokedRenderer(x, y)
        if state == _ROTATE:
            st.StartRotate()
        elif state == _PAN:
            st.StartPan()
        elif state == _DOLLY:
            st.StartDolly()

    def _end_camera(self):
        st = self.style
        s = st.GetState()
        if s == _ROTATE:
            st.EndRotate()
        elif s == _PAN:
            st.EndPan()
        elif s == _DOLLY:
            st.EndDolly()
        elif s == _SPIN:
            st.EndSpin()

    def _move(self, *_):
        if self._camera_busy():
            self.style.OnMouseMove()
        else:
            self._report_mouse()

    def _left_down(self, *_):
        iren = self.interactor
        if iren.GetControlKey() or self.on_mouse is None:
            self._start(_PAN if iren.GetShiftKey() else _ROTATE)
            return
        self.buttons |= LEFT
        self._report_mouse()

    def _left_up(self, *_):
        if self._camera_busy():
            self._end_camera()
            return
        self.buttons &= ~LEFT
        self._report_mouse()

    def _right_down(self, *_):
        iren = self.interactor
        if iren.GetControlKey():
            self._start(_DOLLY)
        elif iren.GetShiftKey():
            self._start(_PAN)
        else:
            self._start(_ROTATE)

    def _middle_down(self, *_):
        self._start(_PAN)

    def _button_up(self, *_):
        self._end_camera()

    def _wheel_fwd(self, *_):
        if self.interactor.GetControlKey() or self.on_mouse is None:
            self.style.OnMouseWheelForward()
        else:
            self.press("depth_in")

    def _wheel_back(self, *_):
        if self.interactor.GetControlKey() or self.on_mouse is None:
            self.style.OnMouseWheelBackward()
        else:
            self.press("depth_out")

    # ------------------------------------------------------------------ keys
    def _key(self, *_):
        sym = self.interactor.GetKeySym() or ""
        action = self.keys.get(sym)
        if action is None and len(sym) == 1:
            action = self.keys.get(sym.lower())
        if action is not None:
            self.press(action)

    def _swallow(self, *_):
        """Keep VTK's default key bindings (wireframe, exit on 'e', ...) out."""
