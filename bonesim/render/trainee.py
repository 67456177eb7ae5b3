"""The trainee's window (``bonesim tutor join`` / ``bonesim tutor playback``).

The trainee's servo runs in its own process (:class:`bonesim.tutoring.trainee.TraineeProcess`);
this window only reads what it publishes, at its own frame rate:

- the tissue: a :class:`~bonesim.engine.replica.TissueReplica` with a surface that
  applies the servo's ``changes`` ring (the tissue events as the instructor
  makes them: removals, resets, splits, poses), drawn with the incremental
  surface update, as the simulator's window draws its own drilling;
- the instructor's tool at its latest pose (the burr turns warm while the
  instructor's drill runs);
- the trainee's hand: a translucent green sphere of the burr's size where
  the trainee's device is;
- the HUD: whom the trainee follows, the instructor's drill, the force on the
  trainee's device, tracking error, latency, servo rate, and ``LINK LOST`` /
  ``PLAYBACK ENDED`` when the source falls silent.

Keys: :data:`TRAINEE_KEYS` (camera gestures as in the simulator's window).
"""
from __future__ import annotations

import math

import numpy as np

from bonesim.engine import events
from bonesim.engine.replica import TissueReplica
from bonesim.net.tutor_protocol import GLOSSARY
from bonesim.render.hud import format_help

__all__ = ["TRAINEE_KEYS", "TRAINEE_MOUSE_HELP", "TraineeView", "TraineeApp"]

#: Key symbol -> action in the trainee's window.
TRAINEE_KEYS = {
    "v": "reset_view", "Home": "reset_view",
    "F12": "screenshot", "c": "screenshot",
    "h": "help", "F1": "help",
    "q": "quit", "Escape": "quit",
}

TRAINEE_MOUSE_HELP = (
    "the tool is the instructor's; the green sphere is your hand",
    "right drag         orbit camera     Ctrl+left drag: orbit",
    "Shift+right, mid   pan              Ctrl+Shift+left: pan",
    "Ctrl+right, Ctrl+wheel  zoom        v: back to the case camera",
)


class TraineeView:
    """Draws a started :class:`~bonesim.tutoring.trainee.TraineeProcess` on a scene.

    Parameters
    ----------
    scene : Scene
        Made from ``proc.model``.
    proc : TraineeProcess

    Attributes
    ----------
    replica : TissueReplica
        The window's copy of the tissue, with its surface.
    grid : Grid
        The replica's grid.
    surface : Surface
        Its surface (rebuilt at a reset, updated incrementally otherwise).
    applied : int
        Removals applied since the last reset.
    resets : int
        ``RESET`` events applied.
    """

    def __init__(self, scene, proc):
        self.scene = scene
        self.proc = proc
        self.model = proc.model
        self.cursor = events.Cursor(proc.changes, start=0)   # from the servo's first event
        self.replica = TissueReplica(self.model, surface=True)
        self.resets = 0
        self.applied = 0
        scene.update_bodies(self.replica)

    @property
    def grid(self):
        return self.replica.grid

    @property
    def surface(self):
        return self.replica.surface

    def drain(self) -> int:
        """Apply the servo's tissue events since the last call; returns the
        removals applied since the last reset among them (all of them
        without a reset)."""
        ev = self.cursor.drain()
        if len(ev["kind"]) == 0:
            return 0
        ch = self.replica.apply(ev)
        rem = ch.removed
        if ch.reset:                         # a new surface: drawn in full
            self.resets += int(np.count_nonzero(ev["kind"] == events.RESET))
            self.applied = len(rem)
            self.scene.update_bodies(self.replica)
        else:
            self.applied += len(rem)
            if len(rem) or ch.bodies:        # removals, or bodies split off / moved
                self.scene.update_bodies(self.replica, ch.changed, None)
        return len(rem)

    def hud_info(self) -> dict:
        """What the HUD shows, from the servo's status."""
        s = self.proc.status
        p = self.proc
        burr = int(s["burr"])
        names = p.burrs
        info = {"case": self.model.name, "following": p.what}
        if 0 <= burr < len(names):
            info["burr"] = names[burr]
        info["drill"] = bool(s["drill"])
        info["direction"] = int(s["direction"])
        info["speed_rpm"] = float(s["speed_rpm"])
        info["force_n"] = float(np.linalg.norm(s["force_n"]))
        t = float(s["t_s"])
        info["haptic_hz"] = int(s["ticks"]) / t if t > 0 else 0.0
        err = float(s["err_mm"])
        info["tracking error"] = "-" if math.isnan(err) else f"{err:.1f} mm"
        if p.source[0] == "network":
            lat = float(s["latency_ms"])
            info["latency"] = "-" if math.isnan(lat) else f"{lat:.2f} ms"
        else:
            info["playback"] = (f"{float(s['playback_s']):.1f} / "
                                f"{p.duration_of_source_s:.1f} s")
        info["removed"] = self.applied
        if s["done"]:
            info["message"] = f"{p.lost_text}: the session is over (q quits)"
        elif s["lost"]:
            info["message"] = p.lost_text
            if p.source[0] == "network":             # what the words mean, on the HUD
                info["message"] += " - " + GLOSSARY["link lost"].split(": ", 1)[1]
        return info

    def show(self) -> dict:
        """Bring the view up to the servo's latest state (the caller renders);
        returns the HUD info."""
        self.drain()
        s = self.proc.status
        sc = self.scene
        r = self.proc.radius_mm(int(s["burr"]))
        if s["valid"]:
            sc.set_tool(s["instr_pos_mm"],
                        s["instr_axis"], r, bool(s["drill"]))
            sc.set_marker(s["hand_mm"], r)
        info = self.hud_info()
        sc.set_hud(info)
        return info


class TraineeApp:
    """The trainee's window around a started :class:`~bonesim.tutoring.trainee.TraineeProcess`.

    Parameters
    ----------
    proc : TraineeProcess
    size : (int, int)
        Window size [px].
    offscreen : bool
        Render without a display (tests, screenshots).
    """

    def __init__(self, proc, *, size=(1280, 720), offscreen: bool = False):
        self.proc = proc
        self.size = tuple(size)
        self.offscreen = bool(offscreen)
        self.scene = self.window = self.view = None

    def start(self) -> "TraineeApp":
        from bonesim.render.scene import Scene
        from bonesim.render.window import Window

        self.scene = Scene.from_model(self.proc.model, offscreen=self.offscreen,
                                      size=self.size, title="bonesim trainee")
        self.view = TraineeView(self.scene, self.proc)
        self.window = Window(self.scene, self.on_frame, keys=TRAINEE_KEYS)
        self.scene.set_help(format_help(TRAINEE_KEYS, TRAINEE_MOUSE_HELP))
        self.view.show()
        return self

    def on_frame(self, scene) -> None:
        self.view.show()

    def run(self, frames: int | None = None, screenshot=None) -> dict:
        """Run the window until quit (or ``frames`` frames); offscreen runs
        ``frames`` frames in real time (default: until the servo ends).
        Returns a summary."""
        if self.offscreen:
            n = frames if frames is not None else 10 ** 9
            self.window.on_frame = self._until_done
            out = self.window.run_offscreen(n, screenshot=screenshot, realtime=True)
        else:
            out = self.window.run(max_frames=frames)
            if screenshot is not None:
                out["screenshot"] = str(self.scene.screenshot(screenshot))
        out.update({"removed": self.view.applied, "resets": self.view.resets,
                    "hud": self.scene.hud_text})
        return out

    def _until_done(self, scene) -> None:
        done = self.proc.done            # read before the last drain: nothing after it
        self.view.show()
        if done:
            self.window.quit()

    def close(self) -> None:
        if self.scene is not None:
            self.scene.close()
            self.scene = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
