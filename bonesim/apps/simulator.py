"""The interactive simulator: window, haptic loop, sound and dust together.

:class:`App` wires the subsystems; ``bonesim run`` drives it.

* The haptic loop (:mod:`bonesim.runtime.haptic_loop`) runs in its own process at
  1 kHz with the device: the mouse/keyboard device (the window writes the
  target, a virtual coupling keeps the burr on the bone) or a scripted
  trajectory.
* The sound (:mod:`bonesim.runtime.audio`) runs in a third process, steered by the
  loop's shared status.
* The window's frame callback (main thread) drains the loop's rings into the
  hybrid surface and the bone dust, moves the tool, and fills the HUD. It
  never blocks the loop: it only reads what the loop has published.

* The nerve monitor (:mod:`bonesim.runtime.monitor`), when the case monitors a
  nerve, runs in a fourth process on the loop's samples: its scrolling trace
  is drawn over the window (``m`` shows or hides it), its clicks are mixed
  into the sound, and with ``monitor_serve`` it streams to remote consoles
  (``bonesim monitor HOST``, :mod:`bonesim.net.monitor_link`).

Mouse and keys: the mouse moves the tool in the view plane; the wheel (or
Up/Down) sets how hard the hand presses along the view, in millimetres of
coupling-spring stretch (1 mm = 1 N with the default coupling): at 0 the burr
hovers, above 0 it sinks until it rests on bone and drills its way in.
``k`` makes the cut plane the tool (drill off): the mouse moves its
rectangle, facing the view, through the view plane; Return cuts a stroke
(:class:`bonesim.runtime.commands.CutPlane`); ``k`` again gives the burr back.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.engine.cut_plane import plane_pose
from bonesim.physics.dust.water import water_sprites
from bonesim.physics.sightline import depth_below_surface_mm
from bonesim.runtime.commands import CutPlane
from bonesim.runtime.haptic_loop import HapticLoop

__all__ = ["PRESS_STEP_MM", "SPEED_STEP_RPM", "START_STANDOFF_MM", "RATE_EVERY_FRAMES",
           "SUCTION_RADIUS_MM", "WATER_SPREAD_MM", "CUT_WIDTH_MM", "CUT_HEIGHT_MM",
           "CUT_DEPTH_MM", "CUT_STANDOFF_MM", "App", "DISTRACT_STEP_MM", "RIGID_ACTIONS"]

#: Press depth change per wheel click or Up/Down key [mm] (1 mm = 1 N).
PRESS_STEP_MM = 0.5
#: Spindle speed change per key press [rpm].
SPEED_STEP_RPM = 5000.0
#: Distractor length change per key press [mm].
DISTRACT_STEP_MM = 0.5
#: Window actions for fragments and plates (:meth:`App._rigid_key`).
RIGID_ACTIONS = ("grab_toggle", "place_plate", "affix_plate", "distract_more",
                 "distract_less")
#: Where the tool starts: this far from the case's focal point toward the eye [mm].
START_STANDOFF_MM = 10.0
#: How often the HUD's haptic-rate statistics are recomputed [frames].
RATE_EVERY_FRAMES = 15
#: Suction tip radius [mm].
SUCTION_RADIUS_MM = 1.5
#: How far past the burr's surface the irrigation water wets the dust [mm]
#: (the burr pushes dust out of its own sphere, so the water must reach past it).
WATER_SPREAD_MM = 2.0
#: The cut plane's stroke (``k`` the tool, Return a stroke): width and height
#: of its rectangle, facing the view, and how deep its rays go [mm] ...
CUT_WIDTH_MM, CUT_HEIGHT_MM, CUT_DEPTH_MM = 10.0, 0.5, 4.0
#: ... starting this far in front of the view plane through the tool [mm].
CUT_STANDOFF_MM = 1.0


class App:
    """One simulator session.

    Parameters
    ----------
    case : str
        Case name or ``case.toml`` path.
    burr : str
        Starting burr; the others of the burr table are a key press away.
    script : Trajectory, optional
        Drive the tool from this trajectory instead of the mouse.
    offscreen : bool
        Render without a display.
    size : (int, int)
        Window size [px].
    sound : bool
        Play the drill sound (a silent sink with one notice if there is no
        audio device).
    wav : path, optional
        Record the sound to this WAV file.
    record : path, optional
        Record the session to this HDF5 file (:mod:`bonesim.runtime.record`).
    who : dict, optional
        ``participant``, ``group`` and ``notes`` for the recording's header.
    monitor : bool
        Run the nerve monitor when the case monitors a nerve.
    monitor_serve : dict, optional
        Stream the monitor to remote consoles: ``key`` (bytes), ``host``,
        ``port`` (see :class:`bonesim.net.monitor_link.MonitorServer`).
    stereo : str, optional
        Stereo view mode (:data:`bonesim.render.stereo.STEREO_MODES`).
    eye_separation_mm : float, optional
        Distance between the eyes for stereo [mm] (default from
        ``render.toml``).
    force_limits : path or ForceLimits, optional
        Per-distance force and speed limits near a structure
        (:mod:`bonesim.physics.force_limits`; ``bonesim metrics limits``
        writes them): the HUD warns when a removal near the structure goes
        above them.
    fragments : bool
        Split off bone that drilling cuts free (a background
        :class:`~bonesim.runtime.fragment_finder.FragmentFinder` thread; its
        commands are sent from the frame callback). Default on.
    device : str, optional
        A device backend (:mod:`bonesim.devices.registry`) instead of the
        mouse, with the user's settings and calibration; it runs behind the
        safety layer and the mouse takes over while it is unplugged.
    pedal : str, optional
        A foot pedal backend (``pedal``) for drill on/off and speed.
    """

    def __init__(self, case: str, burr: str, *, script=None, offscreen: bool = False,
                 size=(1024, 768), sound: bool = True, wav=None, record=None,
                 who: dict | None = None, monitor: bool = True,
                 monitor_serve: dict | None = None, stereo: str | None = None,
                 eye_separation_mm: float | None = None, force_limits=None,
                 fragments: bool = True, device: str | None = None,
                 pedal: str | None = None):
        from bonesim.io.burrs import list_burrs, load_burr
        from bonesim.io.loading import load_model

        chosen = load_burr(burr)
        table = list_burrs()
        names = [b.name for b in table]
        if chosen.name not in names:
            table.insert(0, chosen)
            names.insert(0, chosen.name)
        i0 = names.index(chosen.name)
        self.burrs = table[i0:] + table[:i0]          # index 0 = the chosen burr
        self.device_name = device
        self.device_record = None
        if device is not None:
            from bonesim.io.case import load_case

            if script is not None:
                raise BonesimError("--device and --script both drive the tool; choose one",
                                   field="--device")
            cam = load_case(case).camera
            view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
            start = np.asarray(cam.focal_mm, float) \
                - START_STANDOFF_MM * view / np.linalg.norm(view)
            back = -view / np.linalg.norm(view)
            right = np.cross(-back, cam.up)
            right /= np.linalg.norm(right)
            backend = self._make_backend(device, start, (right, np.cross(back, right), back))
            self.model = load_model(case, chosen, device=backend.caps)
        else:
            self.model = load_model(case, chosen)
        cam = self.model.case.camera
        view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
        self.view = view / np.linalg.norm(view)
        device = ("mouse",) if script is None else ("scripted", script)
        if self.device_name is not None:
            device = ("device", backend)
        self.scripted = script is not None
        pedal_dev = None
        if pedal is not None:
            from bonesim.devices.registry import AUXILIARY, device_record, make_device
            if pedal not in AUXILIARY:
                raise BonesimError(f"{pedal!r} is no pedal; --pedal takes one of "
                                   f"{', '.join(AUXILIARY)}", field="--pedal")
            pedal_dev = make_device(pedal, pedal_ok=True)
            from bonesim.devices.registry import probe

            probe(pedal, pedal_dev)        # the handle's own calibration, for the header
            self.device_record = dict(self.device_record or {"backend": "mouse"},
                                      pedal=device_record(pedal, pedal_dev))
        self.loop = HapticLoop(self.model, burrs=self.burrs[1:], device=device,
                               pedal=pedal_dev)
        self.loop.set_target(np.asarray(cam.focal_mm, float)
                             - START_STANDOFF_MM * self.view, self.view)
        self.press_mm = 0.0
        self.suction = False
        self.suction_pos = None
        self.irrigation = False
        self.cut_pose = None                  # the cut plane's pose while it is the tool
        self.stereo = stereo
        self.eye_separation_mm = eye_separation_mm
        self.offscreen = offscreen
        self.size = size
        self.sound = sound or wav is not None
        self.wav = wav
        self.audio = None
        self.notices: list[str] = []
        self.injuries: list[str] = []
        self.frames = 0
        self.t_start = None
        self._rates = {}
        self.scene = self.window = None
        self.record = None if record is None else Path(record)
        self.who = dict(who or {})
        self.recorder = None
        self.recording = None
        self._record_said = False
        from bonesim.runtime.monitor import monitored_structures

        self.monitor = None
        self.trace = None
        self.want_monitor = monitor and bool(monitored_structures(self.model))
        try:                       # a refusal here must not leave the loop's memory
            self._checked_options(monitor_serve, force_limits)
        except BaseException:
            self.loop.close()
            raise
        self.want_fragments = bool(fragments)
        self.fragments = None

    def _checked_options(self, monitor_serve, force_limits) -> None:
        """The nerve monitor's server and the force limits, checked against
        the case (one-line errors naming the option or file)."""
        if monitor_serve is not None and not self.want_monitor:
            raise BonesimError(f"case {self.model.name!r} monitors no nerve: nothing to "
                               "serve (set monitor = true on a nerve in its case.toml)",
                               field="--monitor-port")
        self.monitor_serve = monitor_serve
        self.watch = None                      # force-near-structure warnings
        if force_limits is not None:
            from bonesim.physics.force_limits import ForceWatch, load_limits

            lim = force_limits if not isinstance(force_limits, (str, Path)) else \
                load_limits(force_limits)
            try:
                self.watch = ForceWatch(self.model, lim)
            except ValueError as exc:
                raise BonesimError(str(exc), path=force_limits if isinstance(
                    force_limits, (str, Path)) else None, field="structure") from None
            if lim.case and lim.case != self.model.name:
                self.notices.append(f"force limits learned on case {lim.case!r}, not "
                                    f"{self.model.name!r}")

    # -------------------------------------------------------------- set-up
    def _make_backend(self, name: str, start_mm, view):
        from bonesim.devices.registry import device_record, make_device, probe

        backend = make_device(name, start_mm=start_mm, view=view)
        probe(name, backend)               # the device's own limits, for model and header
        self.device_record = device_record(name, backend)
        return backend

    def _fresh_consumers(self):
        from bonesim.physics.dust.grid import DustGrid
        from bonesim.engine.replica import TissueReplica

        self.consumer = TissueReplica(self.model, self.loop.state, surface=True)
        self.dust = DustGrid.for_grid(self.consumer.grid, gravity=self.view)

    def start(self) -> "App":
        """Start the haptic (and audio) processes and build the scene."""
        from bonesim.render import gl
        from bonesim.render.scene import Scene
        from bonesim.render.window import Window

        gl.start_probe(offscreen=self.offscreen)      # overlaps with the loop's warm-up
        if self.record is not None:
            from bonesim.runtime.record import Recorder
            from bonesim.session.header import make_header

            header = make_header(self.model, self.burrs[1:],
                                 input_device=self.device_name or (
                                     "scripted" if self.scripted else "mouse"),
                                 device_record=self.device_record, **self.who)
            # the writer reads the loop's rings from record 0, so it may start
            # while the loop warms up
            self.recorder = Recorder(self.loop, self.record, header).start()
        if self.want_monitor:           # warms up beside the loop; reads its samples from 0
            from bonesim.runtime.monitor import MonitorProcess

            self.monitor = MonitorProcess(self.loop, serve=self.monitor_serve).start(wait=False)
        self.loop.start()
        if self.monitor is not None:
            self.monitor.wait_ready()
        if self.sound:
            from bonesim.runtime.audio import AudioProcess

            self.audio = AudioProcess(self.loop, wav=self.wav, monitor=self.monitor).start()
            if self.audio.silent:
                self.notices.append("no audio device: sound muted"
                                    + (f", recorded to {self.wav}" if self.wav else ""))
        self._fresh_consumers()
        if self.watch is not None:          # from the loop's first record, as the recorder
            from bonesim.engine import events

            self._watch_in = (events.Cursor(self.loop.state.tissue, 0),
                              events.Cursor(self.loop.samples, 0))
        if self.want_fragments:
            from bonesim.runtime.fragment_finder import FragmentFinder

            self.fragments = FragmentFinder(self.model, self.loop.state,
                                            self.loop.status).start()
        self.scene = Scene.from_model(self.model, self.consumer.surface,
                                      offscreen=self.offscreen, size=self.size,
                                      stereo_capable=self.stereo == "quad-buffer")
        if self.stereo is not None or self.eye_separation_mm is not None:
            self.scene.set_stereo(self.stereo, self.eye_separation_mm)
        if self.monitor is not None:
            from bonesim.render.trace import MonitorTrace

            v, p = self.monitor.view, self.monitor.params
            self.trace = MonitorTrace(self.scene, v.names, v.colors, max_hz=p.max_hz,
                                      warn_mm=p.warn_mm, baseline_hz=p.baseline_hz)
        self.window = Window(self.scene, self.on_frame, self.on_key, self.on_mouse)
        self.t_start = time.perf_counter()
        return self

    def close(self) -> None:
        if self.fragments is not None:
            self.fragments.close()
            self.fragments = None
        if self.recorder is not None:
            self.recording = self.recorder.close()
            self.recorder = None
            if self.recording["record_error"] and not self._record_said:
                self._say_record(self.recording["record_error"])
            elif self.recording.get("compact_error"):     # complete, left uncompressed
                print(f"bonesim: note: {self.recording['compact_error']}", file=sys.stderr)
        if self.audio is not None:
            self.audio.close()
            self.audio = None
        if self.monitor is not None:
            self.monitor.close()
            self.monitor = None
        self.loop.close()
        if self.scene is not None:
            self.scene.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    def _say_record(self, line: str) -> None:
        """A recording that stopped early: one line in the window and on stderr."""
        import sys

        self._record_said = True
        self.notices.append(line)
        print(f"bonesim: {line}", file=sys.stderr, flush=True)

    def record_summary(self) -> dict:
        """After :meth:`close`: ``record`` (the file), ``record_ok``,
        ``record_kept`` (what the file holds: ``t0_s``, ``t_s`` [s],
        ``samples``, ``removals``) and ``record_error`` (one line or None);
        empty without a recording."""
        if self.record is None or self.recording is None:
            return {}
        r = self.recording
        out = {"record": str(self.record), "record_ok": r["record_ok"],
               "record_kept": r["record_kept"], "record_error": r["record_error"]}
        if r.get("compact_error"):
            out["record_compact_error"] = r["compact_error"]
        return out

    # -------------------------------------------------------------- frames
    @property
    def burr(self):
        return self.burrs[int(self.loop.status["burr"])]

    def on_frame(self, scene) -> None:
        from bonesim.engine.bodies import all_identity, voxel_bodies
        from bonesim.physics.dust.grid import DustGrid

        st = self.loop.status
        if self.fragments is not None:        # the finder's splits: this thread sends
            try:
                self.fragments.pump(self.loop.send)
            except RuntimeError as exc:       # its thread failed: say so, drill on
                self.notices.append(f"fragments off ({exc})")
                self.fragments.close()
                self.fragments = None
        ch = self.consumer.drain()
        if ch.reset:                                   # the case was reset
            self.dust = DustGrid.for_grid(self.consumer.grid, gravity=self.view)
            self.injuries.clear()
        rem, tch = ch.removed, ch.touched
        scene.update_bodies(self.consumer, ch.changed, tch)      # every body at its pose
        pos = st["pos_mm"].copy()
        axis = st["axis"].copy()
        burr = self.burr
        bodies = self.consumer.state            # removals and walls per body
        if len(rem):
            self.dust.add_removed(rem, body=None if all_identity(bodies) else
                                  voxel_bodies(self.consumer.grid, bodies.body, rem),
                                  bodies=bodies)
        dt = 1.0 / self.window.frame_hz
        suction = self.suction_pos if self.suction else None
        self.dust.step(self.consumer.grid, dt, tool_pos_mm=pos, tool_radius_mm=burr.radius_mm,
                       suction_pos_mm=suction,
                       suction_radius_mm=SUCTION_RADIUS_MM if suction is not None else 0.0,
                       irrigation_pos_mm=pos if self.irrigation else None,
                       irrigation_radius_mm=(burr.radius_mm + WATER_SPREAD_MM
                                             if self.irrigation else 0.0),
                       bodies=bodies)
        scene.set_dust(*self.dust.sprites())
        if self.dust.water is not None:                # irrigation water, pooled
            scene.set_water(*water_sprites(self.dust))
        drill = bool(st["drill"])
        depth = depth_below_surface_mm(self.consumer.grid, pos, scene.camera_pose()[0],
                                       burr.radius_mm)
        scene.set_tool(pos, axis, burr.radius_mm, drill, depth_mm=depth)
        scene.set_cut_plane(self.cut_pose, CUT_WIDTH_MM, CUT_HEIGHT_MM, CUT_DEPTH_MM)
        if suction is not None:                   # the suction tip where the mouse is
            scene.set_suction(suction, self.view, SUCTION_RADIUS_MM)
        else:
            scene.set_suction(None)
        self._device_camera(scene, dt)
        if self.recorder is not None:
            self.recorder.camera(*scene.camera_pose())
            line = self.recorder.check()          # the writer died or stopped: say so
            if line is not None:
                self._say_record(line)
        inj = ch.injuries
        for lab in inj["label"]:
            name = self.model.structure_name(int(lab))
            if name not in self.injuries:
                self.injuries.append(name)
        if self.frames % RATE_EVERY_FRAMES == 0:
            self._rates = self.loop.rate_stats(1000)
        scene.set_hud({
            "case": self.model.name, "burr": burr.name, "burr_kind": burr.kind,
            "burr_diameter_mm": burr.diameter_mm,
            "tool": "suction" if self.suction else "cut plane" if self.cut_pose is not None
            else "burr",
            "irrigation": self.irrigation, "depth_mm": depth,
            "drill": drill, "direction": int(st["direction"]), "speed_rpm": float(st["speed_rpm"]),
            "force_n": float(np.linalg.norm(st["force_n"])),
            "haptic_hz": self._rates.get("rate_hz", 0.0),
            "elapsed_s": time.perf_counter() - self.t_start,
            "injuries": list(self.injuries),
            "visible": self._visible(),
            "force_limit": self._force_limit(float(st["t_s"])),
            "message": "; ".join(self.notices) if self.notices else None,
            "device": self._device_status(),
            **self._pedal_status(),
        })
        if self.trace is not None:          # after the HUD: the panel keeps clear of it
            self.trace.update(self.monitor.view.history(self.trace.window_s))
        self.frames += 1

    def _force_limit(self, now_s: float):
        """The HUD's force-near-structure line: what the :class:`ForceWatch`
        found in the loop's new removals and samples (None without limits)."""
        if self.watch is None:
            return None
        from bonesim.engine.events import RingOverflow
        from bonesim.physics.force_limits import WARN_HOLD_S

        new = []
        for cur in self._watch_in:
            try:
                new.append(cur.drain())
            except RingOverflow:        # the window stalled a whole ring: go on from now
                cur.pos = cur.ring.count
                new.append(None)
        self.watch.feed(*new)
        last = self.watch.last
        active = last is not None and now_s - last.t_s <= WARN_HOLD_S
        return {"structure": self.watch.limits.structure, "count": sum(self.watch.count.values()),
                "warning": last if active else None}
    def _device_camera(self, scene, dt: float) -> None:
        """A rate device in camera mode pans [mm/s] and orbits [deg/s] the view."""
        if self.loop.device[0] != "device":
            return
        rate = self.loop.status["camera_rate"]
        if not rate.any():
            return
        eye, focal, up = (np.asarray(x, float) for x in scene.camera_pose())
        shift = rate[:3] * dt
        w = np.radians(rate[3:]) * dt
        a = float(np.linalg.norm(w))
        if a > 0:
            k = w / a

            def turn(v):
                return v * np.cos(a) + np.cross(k, v) * np.sin(a) \
                    + k * float(k @ v) * (1 - np.cos(a))
            eye = focal + turn(eye - focal)
            up = turn(up)
        scene.set_camera(eye + shift, focal + shift, up,
                         view_angle_deg=scene.camera.GetViewAngle())

    def _pedal_status(self) -> dict:
        """``{"pedal": text}`` for the HUD while a foot pedal (or handle) is
        unplugged (the drill is off); changes are noted in the recording."""
        if self.loop.pedal is None:
            return {}
        gone = int(self.loop.status["pedal"]) == 2
        if gone != getattr(self, "_pedal_gone", False):
            self._pedal_gone = gone
            if self.recorder is not None:
                self.recorder.event("pedal", "unplugged" if gone else "connected")
        out = {"pedal": "UNPLUGGED - drill off"} if gone else {}
        from bonesim.session.playback import handle_text

        angles = handle_text(self.loop.status["handle_deg"])   # an instrumented handle's
        if angles is not None and not gone:                      # (stale while away)
            out["handle"] = angles
        return out

    def _device_status(self):
        """``(name, state, rejected)`` of a real device (None for the mouse or a
        script); a change of state is noted in the recording as a UI event."""
        if self.loop.device[0] != "device":
            return None
        from bonesim.devices.safety import STATES

        st = self.loop.status
        state = STATES[int(st["device_state"])]
        seen = (state, int(st["device_unplugs"]))
        if seen != getattr(self, "_device_seen", None):
            if self.recorder is not None:
                if seen[1] != getattr(self, "_device_seen", (None, 0))[1]:
                    self.recorder.event("device", "unplugged")   # however short
                self.recorder.event("device", state)
            self._device_seen = seen
        return self.device_name, state, int(st["device_rejected"])

    def _visible(self):
        """``(visible, judged)`` removals since the case reset, as the
        recorder's visibility judge counts them (None without a recording, or
        once it stopped: its counts no longer follow the run)."""
        if self.recorder is None or self.recorder.failure is not None:
            return None
        st = self.recorder.status
        return int(st["visible"]), int(st["visible"]) + int(st["hidden"])

    def on_mouse(self, world_mm, buttons) -> None:
        if self.scripted:
            return
        if self.suction:
            self.suction_pos = np.asarray(world_mm, float)
            return
        if self.cut_pose is not None:             # the plane faces the view, into the bone
            self.cut_pose = plane_pose(np.asarray(world_mm, float) - CUT_STANDOFF_MM
                                       * self.view, self.view, self.cut_pose_u())
            return
        self.loop.set_target(np.asarray(world_mm, float) + self.press_mm * self.view,
                             self.view)

    def cut_pose_u(self):
        """The cut plane's width axis: the screen's horizontal."""
        return np.cross(self.view, self.scene.camera_pose()[2])

    def on_key(self, action: str) -> bool:
        if self.recorder is not None:
            self.recorder.event("key", action)
        loop, st, ctl = self.loop, self.loop.status, self.loop.control
        if action in ("next_burr", "previous_burr"):
            step = 1 if action == "next_burr" else -1
            loop.set_burr((int(st["burr"]) + step) % len(self.burrs))
        elif action == "drill_toggle":
            loop.set_drill(not bool(ctl["drill"]))
        elif action == "reverse":
            loop.set_drill(bool(ctl["drill"]), direction=-1 if ctl["direction"] >= 0 else 1)
        elif action in ("speed_up", "speed_down"):
            b = self.burr
            sign = 1 if action == "speed_up" else -1
            rpm = float(np.clip(ctl["speed_rpm"] + sign * SPEED_STEP_RPM, 0.0, b.max_speed_rpm))
            loop.set_drill(bool(ctl["drill"]), speed_rpm=rpm)
        elif action == "suction":
            self.suction = not self.suction
        elif action == "irrigation":
            self.irrigation = not self.irrigation
        elif action == "reset_case":
            loop.reset()
        elif action == "cut_plane":
            on = self.cut_pose is None
            loop.set_tool("cutplane" if on else "drill")
            if on:
                loop.set_drill(False)
                self.cut_pose = plane_pose(np.asarray(st["pos_mm"], float) - CUT_STANDOFF_MM
                                           * self.view, self.view, self.cut_pose_u())
            else:
                self.cut_pose = None
        elif action == "cut_stroke":
            if self.cut_pose is not None:
                loop.send(CutPlane, pose=self.cut_pose, width_mm=CUT_WIDTH_MM,
                          height_mm=CUT_HEIGHT_MM, depth_mm=CUT_DEPTH_MM)
        elif action == "nerve_monitor":
            if self.trace is not None:
                self.trace.set_visible(not self.trace.visible)
        elif action in ("depth_in", "depth_out"):
            self.press_mm += PRESS_STEP_MM if action == "depth_in" else -PRESS_STEP_MM
        elif action in RIGID_ACTIONS:
            self._rigid_key(action)
        else:
            return False                               # help, screenshot, quit, view
        return True

    def _rigid_key(self, action: str) -> None:
        """Fragments and plates: grab / let go of what the tool touches, the
        next catalogue plate at the tool, affix it, lengthen or shorten the
        distractor (:mod:`bonesim.runtime.rigid_commands`); a refusal shows
        in the loop's ``command_error``."""
        from bonesim.runtime import rigid_commands as rc

        st = getattr(self, "_rigid_ui", None)
        if st is None:
            st = self._rigid_ui = {"grabbed": False, "plate": 0, "length_mm": 0.0}
        if action == "grab_toggle":
            self.loop.send(rc.ReleaseBody if st["grabbed"] else rc.GrabBody)
            st["grabbed"] = not st["grabbed"]
        elif action == "place_plate":
            from bonesim.io.plates import default_plates

            self.loop.send(rc.PlacePlate, plate=st["plate"])
            st["plate"] = (st["plate"] + 1) % len(default_plates())
            st["length_mm"] = 0.0
        elif action == "affix_plate":
            self.loop.send(rc.AffixPlate)
        else:
            st["length_mm"] += DISTRACT_STEP_MM if action == "distract_more" \
                else -DISTRACT_STEP_MM
            self.loop.send(rc.Distract, length_mm=st["length_mm"])

    # ----------------------------------------------------------------- run
    def run(self, frames: int | None = None, screenshot=None) -> dict:
        """Run the window (or ``frames`` offscreen frames); returns a summary."""
        if self.offscreen:
            out = self.window.run_offscreen(frames or 1, screenshot=screenshot, realtime=True)
        else:
            out = self.window.run(max_frames=frames)
            if screenshot is not None:
                out["screenshot"] = str(self.scene.screenshot(screenshot))
        rates = self.loop.rate_stats(5000)
        out.update({
            "case": self.model.name, "burr": self.burr.name,
            "haptic_rate_hz": round(rates["rate_hz"], 1),
            "haptic_period_p99_ms": round(rates["period_p99_ms"], 3),
            "voxels_removed": int(self.loop.state.removed_by_label.sum()),
            "triangles": int(self.consumer.surface.n_triangles),
            "surface_updates": len(self.consumer.update_s),
            "hud": self.scene.hud_text,
            "dust_cells": float(round(self.dust.total_cells, 2)),
            "injuries": list(self.injuries),
            "notices": list(self.notices),
        })
        if self.fragments is not None:
            fs = self.fragments.stats
            out["fragments"] = {"rounds": fs["rounds"], "split": fs["split"], "shed": fs["shed"],
                                "bodies": int(self.loop.state.n_bodies)}
        if self.monitor is not None:
            out["monitor"] = self.monitor.stats()
            out["monitor"]["nerves"] = list(self.monitor.names)
            if self.monitor_serve is not None:
                out["monitor"]["port"] = self.monitor.port
            if self.audio is not None:
                out["monitor"]["clicks"] = self.audio.click_stats()
        if self.wav is not None:
            out["wav"] = str(Path(self.wav))
        if self.record is not None:
            out["record"] = str(self.record)
        return out
