"""Drawing a recorded session: the timeline bar, the playback window and the
video export.

The logic (which voxels are gone at time t, where the tool was, what the
HUD says) is :mod:`bonesim.session.playback`; this module only draws it.

:class:`TimelineBar`
    A 2-D overlay along the bottom of the view: the recording as a bar, the
    played part filled, injuries as red (removal) or orange (contact) ticks,
    case resets as white ticks, and the play head. It maps pixels to times
    for clicks and drags.
:class:`PlaybackView`
    Shows a :class:`~bonesim.session.playback.Player` at a time on a
    :class:`~bonesim.render.scene.Scene`: the surface (incremental forward,
    rebuilt backward), the tool at its recorded pose, the HUD, the timeline,
    and the recorded camera (unless the user has orbited away from it).
:class:`PlaybackApp`
    The window (``bonesim playback FILE.h5``): keys :data:`PLAYBACK_KEYS`,
    click or drag on the bar to seek, right-drag to orbit, ``v`` to return
    to the recorded camera.
:func:`export_video`
    Offscreen frames piped to an H.264 mp4 with a progress bar.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkRenderingCore import vtkActor2D, vtkPolyDataMapper2D

from bonesim.session.playback import SEEK_LONG_S, SEEK_SHORT_S, PlaybackClock, hud_info
from bonesim.progress import ProgressBar
from bonesim.session.video import VideoWriter, video_times
from bonesim.render.hud import format_help
from bonesim.render.window import LEFT

__all__ = ["PLAYBACK_KEYS", "PLAYBACK_MOUSE_HELP", "BAR_RGBA", "PLAYED_RGBA",
           "CONTACT_RGBA", "REMOVAL_RGBA", "RESET_RGBA", "HEAD_RGBA", "BAR_MARGIN_PX",
           "bar_rect", "TimelineBar", "PlaybackView", "PlaybackApp", "export_video"]

#: Key symbol -> action in the playback window.
PLAYBACK_KEYS = {
    "space": "play_pause",
    "plus": "speed_up", "equal": "speed_up", "KP_Add": "speed_up",
    "minus": "speed_down", "KP_Subtract": "speed_down",
    "Left": "seek_back_1s", "Right": "seek_forward_1s",
    "Down": "seek_back_10s", "Up": "seek_forward_10s",
    "Prior": "seek_back_10s", "Next": "seek_forward_10s",
    "Home": "seek_start", "End": "seek_end",
    "v": "reset_view",
    "F12": "screenshot", "c": "screenshot",
    "h": "help", "F1": "help",
    "q": "quit", "Escape": "quit",
}

PLAYBACK_MOUSE_HELP = (
    "left click / drag on the bar   seek",
    "right drag         orbit camera     Ctrl+left drag: orbit",
    "Shift+right, mid   pan              Ctrl+Shift+left: pan",
    "Ctrl+right, Ctrl+wheel  zoom        v: back to the recorded camera",
)

#: Timeline colours (RGBA 0-255).
BAR_RGBA = (70, 72, 80, 210)
PLAYED_RGBA = (90, 150, 230, 235)
CONTACT_RGBA = (255, 160, 30, 255)
REMOVAL_RGBA = (240, 40, 30, 255)
RESET_RGBA = (235, 235, 235, 255)
HEAD_RGBA = (255, 255, 255, 255)
#: Distance of the bar from the window's left, right and bottom edges [px].
BAR_MARGIN_PX = 12


def bar_rect(width: int, height: int) -> tuple[int, int, int, int]:
    """Pixel rectangle ``(x0, y0, x1, y1)`` of the timeline bar in a view of
    ``width`` x ``height`` pixels (origin bottom-left)."""
    hb = int(np.clip(round(height / 45.0), 6, 16))
    x0 = BAR_MARGIN_PX
    x1 = max(width - BAR_MARGIN_PX, x0 + 1)
    y0 = BAR_MARGIN_PX
    return x0, y0, x1, y0 + hb


class TimelineBar:
    """The timeline overlay of a scene.

    Parameters
    ----------
    scene : Scene
    timeline : bonesim.session.playback.Timeline
        Supplies the duration, injury and reset times.
    """

    def __init__(self, scene, timeline):
        self.scene = scene
        self.duration = float(timeline.duration)
        self.injury_t = np.asarray(timeline.inj_t, float)
        self.injury_kind = np.asarray(timeline.inj_kind)
        self.reset_t = np.asarray(timeline.reset_t, float)
        self.t = 0.0
        self._pd = vtkPolyData()
        mapper = vtkPolyDataMapper2D()
        mapper.SetInputData(self._pd)
        mapper.SetColorModeToDirectScalars()
        mapper.SetScalarModeToUseCellData()
        mapper.ScalarVisibilityOn()
        self.actor = vtkActor2D()
        self.actor.SetMapper(mapper)
        self.actor.PickableOff()
        scene.renderer.AddViewProp(self.actor)
        self.update(0.0)

    def size(self) -> tuple[int, int]:
        """Size of the 3D view [px] (the bar spans it, left of the side panel)."""
        x0, y0, x1, y1 = self.scene.view_rect()
        return int(x1 - x0), int(y1 - y0)

    def rect(self) -> tuple[int, int, int, int]:
        """The bar's pixel rectangle for the current window size."""
        return bar_rect(*self.size())

    def x_of(self, t) -> np.ndarray:
        """Pixel column of playback time(s) ``t``."""
        x0, _, x1, _ = self.rect()
        t = np.asarray(t, float)
        frac = t / self.duration if self.duration > 0 else np.zeros_like(t)
        return x0 + np.clip(frac, 0.0, 1.0) * (x1 - x0)

    def time_at(self, x: float) -> float:
        """Playback time [s] under pixel column ``x`` (clamped to the bar)."""
        x0, _, x1, _ = self.rect()
        return float(np.clip((float(x) - x0) / (x1 - x0), 0.0, 1.0) * self.duration)

    def hit(self, x: float, y: float, slack_px: int = 6) -> bool:
        """Whether pixel ``(x, y)`` is on the bar (with ``slack_px`` around it)."""
        x0, y0, x1, y1 = self.rect()
        return x0 - slack_px <= x <= x1 + slack_px and y0 - slack_px <= y <= y1 + slack_px

    def top_px(self) -> int:
        """Highest pixel row the overlay draws on."""
        _, y0, _, y1 = self.rect()
        return y1 + max(3, (y1 - y0) // 2)

    def update(self, t: float) -> None:
        """Redraw for playback time ``t`` [s] (and the current window size)."""
        self.t = float(t)
        x0, y0, x1, y1 = self.rect()
        hb = y1 - y0
        ext = max(3, hb // 2)
        quads, rgba = [(x0, y0, x1, y1)], [BAR_RGBA]
        xt = float(self.x_of(self.t))
        if xt > x0:
            quads.append((x0, y0, xt, y1))
            rgba.append(PLAYED_RGBA)
        # ticks, at most one per pixel column and kind (removal drawn over contact)
        for times, colour, lo, hi in (
                (self.reset_t, RESET_RGBA, y0 - ext, y1 + ext),
                (self.injury_t[self.injury_kind != 1], CONTACT_RGBA, y0 - ext, y1 + ext),
                (self.injury_t[self.injury_kind == 1], REMOVAL_RGBA, y0 - ext, y1 + ext)):
            if len(times) == 0:
                continue
            for x in np.unique(np.round(self.x_of(times))):
                quads.append((x - 1, lo, x + 1, hi))
                rgba.append(colour)
        quads.append((xt - 1.5, y0 - ext - 2, xt + 1.5, y1 + ext + 2))
        rgba.append(HEAD_RGBA)
        q = np.asarray(quads, float)
        pts = np.zeros((len(q), 4, 3), np.float32)
        pts[:, 0, :2] = q[:, [0, 1]]
        pts[:, 1, :2] = q[:, [2, 1]]
        pts[:, 2, :2] = q[:, [2, 3]]
        pts[:, 3, :2] = q[:, [0, 3]]
        points = vtkPoints()
        points.SetData(numpy_support.numpy_to_vtk(pts.reshape(-1, 3), deep=True))
        conn = np.arange(4 * len(q), dtype=np.int64)
        offs = np.arange(0, 4 * len(q) + 1, 4, dtype=np.int64)
        cells = vtkCellArray()
        cells.SetData(numpy_support.numpy_to_vtkIdTypeArray(offs, deep=True),
                      numpy_support.numpy_to_vtkIdTypeArray(conn, deep=True))
        col = numpy_support.numpy_to_vtk(np.asarray(rgba, np.uint8), deep=True)
        col.SetName("rgba")
        self._pd.SetPoints(points)
        self._pd.SetPolys(cells)
        self._pd.GetCellData().SetScalars(col)
        self._pd.Modified()


class PlaybackView:
    """Shows a :class:`~bonesim.session.playback.Player` on a scene.

    Parameters
    ----------
    scene : Scene
        Made from the player's model and surface.
    player : bonesim.session.playback.Player
    notices : sequence of str
        Lines always shown in the HUD (e.g. an incomplete recording).
    video : bool
        Frames for a video: the HUD shows no measured frame rate.

    Attributes
    ----------
    follow : bool
        The camera follows the recorded camera stream (False once the user
        moves the camera; :meth:`recorded_view` sets it again).
    bar : TimelineBar
    """

    def __init__(self, scene, player, *, notices=(), video: bool = False):
        self.scene = scene
        self.player = player
        self.notices = list(notices)
        self.video = bool(video)
        self.bar = TimelineBar(scene, player.timeline)
        self.follow = True
        self._cam_sig = None
        self._drawn = None
        self.has_camera_stream = player.timeline.cam_t.shape[0] > 0
        self._sync_surface({"mode": "rebuild", "removed": None})

    def _sync_surface(self, seek: dict) -> None:
        surf = self.player.surface
        rep = self.player.replica
        if surf is not self._drawn:
            self.scene.update_bodies(rep)              # every body at its pose
            self._drawn = surf
        elif seek["mode"] == "forward":
            self.scene.update_bodies(rep, seek["removed"], None)

    def show(self, t: float, *, speed: float | None = None, playing: bool | None = None):
        """Bring everything to playback time ``t``; returns the
        :class:`~bonesim.session.playback.Frame` shown (the caller renders)."""
        seek = self.player.seek(t)
        self._sync_surface(seek)
        f = self.player.frame()
        sc = self.scene
        sc.set_tool(f.pos_mm, f.axis, float(getattr(f.burr, "radius_mm", 1.0)), f.drill)
        info = hud_info(f, self.player.model, speed=speed, playing=playing,
                        notices=self.notices)
        if self.video:
            info["frame_hz"] = None
        if sc.panel_renderer is None:       # HUD over the view: keep it above the bar
            sc.text_bottom_px = self.bar.top_px()
        sc.set_hud(info)
        self.bar.update(f.t_s)
        self._camera(f)
        return f

    def _signature(self):
        c = self.scene.camera
        return np.array(c.GetPosition() + c.GetFocalPoint() + c.GetViewUp())

    def _camera(self, f) -> None:
        if f.camera is None or not self.follow:
            return
        if self._cam_sig is not None:
            sig = self._signature()
            scale = max(1.0, float(np.abs(self._cam_sig).max()))
            if np.abs(sig - self._cam_sig).max() > 1e-6 * scale:
                self.follow = False            # the user moved the camera: leave it
                return
        self.scene.set_camera(*f.camera)
        self._cam_sig = self._signature()

    def recorded_view(self) -> None:
        """Follow the recorded camera again (or, without a stream, go back
        to the case camera)."""
        self.follow = True
        self._cam_sig = None
        if self.has_camera_stream:
            self._camera(self.player.frame())
        else:
            self.scene.reset_camera()


class PlaybackApp:
    """The playback window of a session.

    Parameters
    ----------
    player : bonesim.session.playback.Player
    size : (int, int)
        Window size [px].
    offscreen : bool
        Render without a display (tests, screenshots).
    speed : float
        Start speed.
    start : float
        Start time [s].
    play : bool
        Start playing.
    notices : sequence of str
        Always shown in the HUD.
    clock : callable
        Wall-clock source [s] (tests pass a fake one).
    """

    def __init__(self, player, *, size=(1280, 720), offscreen: bool = False,
                 speed: float = 1.0, start: float = 0.0, play: bool = True, notices=(),
                 clock=time.perf_counter):
        self.player = player
        self.size = tuple(size)
        self.offscreen = bool(offscreen)
        self.clock = PlaybackClock(player.timeline.duration, start, speed, play)
        self.notices = list(notices)
        self.wall = clock
        self._last = None
        self.dragging = False
        self.scene = self.window = self.view = None

    def start(self) -> "PlaybackApp":
        from bonesim.render.scene import Scene
        from bonesim.render.window import Window

        self.scene = Scene.from_model(self.player.model, self.player.surface,
                                      offscreen=self.offscreen, size=self.size,
                                      title="bonesim playback")
        self.view = PlaybackView(self.scene, self.player, notices=self.notices)
        self.window = Window(self.scene, self.on_frame, self.on_key, self.on_mouse,
                             keys=PLAYBACK_KEYS)
        self.scene.set_help(format_help(PLAYBACK_KEYS, PLAYBACK_MOUSE_HELP))
        self.view.show(self.clock.t, speed=self.clock.speed, playing=self.clock.playing)
        return self

    def close(self) -> None:
        if self.scene is not None:
            self.scene.close()
            self.scene = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    # ---------------------------------------------------------- callbacks
    def on_frame(self, scene) -> None:
        now = self.wall()
        if self._last is not None and not self.dragging:
            self.clock.advance(now - self._last)
        self._last = now
        self.view.show(self.clock.t, speed=self.clock.speed, playing=self.clock.playing)

    def on_key(self, action: str) -> bool:
        c = self.clock
        if action == "play_pause":
            c.toggle()
        elif action == "speed_up":
            c.faster()
        elif action == "speed_down":
            c.slower()
        elif action in ("seek_back_1s", "seek_forward_1s", "seek_back_10s",
                        "seek_forward_10s"):
            step = SEEK_LONG_S if action.endswith("10s") else SEEK_SHORT_S
            c.skip(-step if "back" in action else step)
        elif action == "seek_start":
            c.seek(0.0)
        elif action == "seek_end":
            c.seek(c.duration)
        elif action == "reset_view":
            self.view.recorded_view()
        else:
            return False                        # help, screenshot, quit: the window's
        if not self.offscreen:                  # show it now, not at the next tick
            self.view.show(c.t, speed=c.speed, playing=c.playing)
            self.scene.render()
        return True

    def on_mouse(self, world_mm, buttons) -> None:
        x, y = self.window.interactor.GetEventPosition()
        if buttons & LEFT and (self.dragging or self.view.bar.hit(x, y)):
            self.dragging = True
            self.clock.seek(self.view.bar.time_at(x))
        elif not buttons & LEFT:
            self.dragging = False

    # ----------------------------------------------------------------- run
    def run(self, frames: int | None = None, screenshot=None) -> dict:
        """Run the window until quit (or ``frames`` frames); offscreen runs
        ``frames`` frames (default 1). Returns a summary."""
        if self.offscreen:
            out = self.window.run_offscreen(frames or 1, screenshot=screenshot)
        else:
            out = self.window.run(max_frames=frames)
            if screenshot is not None:
                out["screenshot"] = str(self.scene.screenshot(screenshot))
        out.update({"t_s": round(self.clock.t, 3),
                    "duration_s": round(self.player.timeline.duration, 3),
                    "speed": self.clock.speed, "playing": self.clock.playing,
                    "seek_rebuilds": self.player.stats["rebuilds"],
                    "seek_forward": self.player.stats["forward"],
                    "hud": self.scene.hud_text})
        return out


def export_video(player, path, *, fps: float = 30.0, size=(1280, 720), speed: float = 1.0,
                 start: float | None = None, end: float | None = None,
                 progress: bool = True, stream=None, notices=()) -> dict:
    """Render a session offscreen into an H.264 mp4.

    Parameters
    ----------
    player : bonesim.session.playback.Player
    path : path
        Output ``.mp4``.
    fps : float
        Video frame rate [Hz].
    size : (int, int)
        Frame width, height [px] (even).
    speed : float
        Playback speed factor (2: the video lasts half the recording).
    start, end : float, optional
        Part of the recording [s].
    progress : bool
        Draw a progress bar on ``stream`` (default stderr).
    notices : sequence of str
        Lines always shown in the HUD.

    Returns
    -------
    dict
        ``video``, ``frames``, ``size``, ``fps``, ``speed``, ``start_s``,
        ``end_s``, ``wall_s``, ``frames_per_s`` (export rate).

    Raises
    ------
    BonesimError
        Bad times or size, unwritable output, ffmpeg failing.
    """
    from bonesim.render.scene import Scene

    times = video_times(player.timeline.duration, fps, speed, start, end)
    w, h = int(size[0]), int(size[1])
    t_wall = time.perf_counter()
    with VideoWriter(path, (w, h), fps) as vw:   # checks the path before rendering
        player.seek(float(times[0]))
        scene = Scene.from_model(player.model, player.surface, offscreen=True, size=(w, h),
                                 visible_subset=False, title="bonesim video")
        bar = ProgressBar(len(times), "video", stream=stream) if progress else None
        try:
            view = PlaybackView(scene, player, notices=notices, video=True)
            for k, t in enumerate(times):
                view.show(float(t), speed=speed)
                img = scene.image()
                if img.shape[:2] != (h, w):
                    raise RuntimeError(f"the offscreen frame is {img.shape[1]}x{img.shape[0]}"
                                       f" px, asked for {w}x{h}")
                vw.write(img)
                if bar is not None:
                    bar.update(k + 1)
        finally:
            scene.close()
            if bar is not None:
                bar.close()
    wall = time.perf_counter() - t_wall
    return {"video": str(Path(path)), "frames": int(len(times)), "size": [w, h],
            "fps": float(fps), "speed": float(speed), "start_s": round(float(times[0]), 4),
            "end_s": round(float(times[-1]), 4), "wall_s": round(wall, 3),
            "frames_per_s": round(len(times) / wall, 2) if wall > 0 else 0.0}
