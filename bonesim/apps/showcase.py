"""The headless main job: the planned mastoidectomy, drilled in simulated time.

``bonesim run`` without a display (or ``--offscreen`` without a script)
runs this: the demo plan (:func:`bonesim.io.toolpath.demo_trajectory`: layered
raster passes along the surgeon's view, drill off between layers for
irrigation and suction) is fed to :func:`bonesim.engine.world.world_step` at
the haptic rate in this process, and frames are drawn at fixed points of *simulated*
time. Frames follow the simulation, not the other way round, so the result
(what was drilled, the pictures) is the same on an idle machine and on a
busy one; only the wall time differs.

Each frame drains the removals into the hybrid surface and the bone dust,
moves the dust (gravity, the burr's push, irrigation, suction), updates the
nerve monitor's trace from the steps since the previous frame, and renders
the scene offscreen. The frames become a short time-lapse video (H.264,
:class:`bonesim.session.video.VideoWriter`) and the last one the final picture.
:func:`run_showcase` runs these stages of consecutive frames side by side
(:func:`advance_through`): while the engine steps frame ``i + 1``, a worker
thread moves the dust of frame ``i`` on a copy of the bone taken when its
steps ended, and another draws and encodes frame ``i - 1``
(:mod:`bonesim.apps.frames`; numba's kernels and VTK's software OpenGL run
without the GIL). Each stage reads only what was captured for its frame, in
the order :meth:`Showcase.advance` runs them, so the frames are the same as
drawing them in line, in less wall time on two cores.
"""
from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np

from bonesim.engine import events
from bonesim.runtime.simulate import CLEARANCE_EVERY, closest_approach

__all__ = ["VIDEO_S", "VIDEO_FPS", "SIZE", "DUST_DT_S", "MONITOR_DT_S", "PLAN_AHEAD_S",
           "Frame", "Showcase", "advance_through", "run_showcase"]

#: Length of the time-lapse video [s] (the plan's minutes are sped up to fit).
VIDEO_S = 16.0
#: Its frame rate [Hz].
VIDEO_FPS = 25.0
#: Frame size [px] (width, height; even for H.264).
SIZE = (1280, 720)
#: Longest dust step [s of simulated time]; a frame's interval is split into
#: steps no longer than this.
DUST_DT_S = 1.0 / 30.0
#: Interval of the nerve monitor's updates [s of simulated time] (its
#: process updates at 50 Hz in an interactive run).
MONITOR_DT_S = 0.02
#: The camera moves this many times closer to the case's focal point than
#: the case camera (the cavity, not the whole bone, fills the frame).
ZOOM = 1.5
#: Suction tip radius [mm] (as the app's suction tool).
TIP_RADIUS_MM = 1.5
#: Radius of the patch the irrigation water wets around its tip [mm] (the
#: water runs over the cavity's floor below the tip).
WATER_RADIUS_MM = 4.0
#: While the burr cuts, the other hand's suction-irrigator follows it, as
#: surgeons work: its water lands on the burr and its tip trails the burr
#: along its path by this much time [s] (the paste just made shows, then goes).
ASSIST_LAG_S = 0.5
#: How the trailing suction tube is drawn: its radius [mm] (a 7 Fr
#: Frazier tip) and its tilt from the drill axis across the view (it
#: comes in from the other hand) [tan of the angle].
SUCTION_DRAWN_RADIUS_MM = 1.1
SUCTION_TILT = 0.3


class Frame(NamedTuple):
    """What :meth:`Showcase.capture` took of the engine for one frame.

    Attributes
    ----------
    events : dict of str -> ndarray
        Tissue events since the previous frame (:data:`bonesim.engine.events.TISSUE_FIELDS`).
    touched : (m, 3) int32
        Voxels whose density the engine lowered since the previous frame.
    bone : bonesim.engine.grid.Grid
        The engine's grid with a copy of its densities at the frame's moment
        (the dust's walls, the touched voxels' densities).
    q : int
        The last sample stepped.
    t0_s, t_s : float
        The frame's interval of simulated time [s] (the dust's).
    force_n : float
        The HUD's force: the largest over the last ``MONITOR_DT_S`` [N].
    history : tuple or None
        The nerve monitor's history for its trace (None: unchanged).
    """

    events: dict
    touched: np.ndarray
    bone: object
    q: int
    t0_s: float
    t_s: float
    force_n: float
    history: object


#: A run of ``seconds`` plans this much further [s]: the haptic-rate samples
#: up to ``seconds`` interpolate the plan's samples on both sides of them.
PLAN_AHEAD_S = 1.0


class Showcase:
    """A scripted run drawn frame by frame in simulated time.

    Parameters
    ----------
    case : str or Path
        Case name or manifest.
    burr : str
        Burr name or file.
    trajectory : bonesim.io.trajectory.Trajectory, optional
        Tool path (default: the case's demo mastoidectomy).
    size : (int, int)
        Frame size [px].
    monitor : bool
        Show the nerve monitor's trace when the case monitors a nerve.
    seconds : float, optional
        With the demo plan: plan only its first ``seconds`` [s of simulated
        time] and :data:`PLAN_AHEAD_S` more (the same samples as the whole
        plan's, planned in a fraction of the time when short;
        :func:`bonesim.io.toolpath.plan_mastoidectomy`).
    """

    def __init__(self, case="phantom", burr="cutting-5mm", *, trajectory=None,
                 size=SIZE, monitor: bool = True, seconds: float | None = None):
        from bonesim.physics.dust.grid import DustGrid
        from bonesim.io.burrs import load_burr
        from bonesim.io.loading import load_model
        from bonesim.engine.model import make_state
        from bonesim.render.scene import Scene
        from bonesim.engine.replica import TissueReplica
        from bonesim.io.toolpath import plan_mastoidectomy

        model = load_model(case, burr)
        if trajectory is None:                  # the plan: cutting, then diamond burr
            planned = plan_mastoidectomy(
                model.case, model.burr,
                until_s=None if seconds is None else float(seconds) + PLAN_AHEAD_S)
            traj = planned.trajectory
            model = model.with_burrs([load_burr(b) for b in planned.burrs[1:]])
        else:
            traj = trajectory
        if int(traj.burr.max()) >= len(model.burrs):
            raise ValueError(f"the trajectory uses burr {int(traj.burr.max())}; the run "
                             f"has burrs 0..{len(model.burrs) - 1}")
        self.model = model
        self.samples = traj.resample(model.haptic_rate_hz)
        if len(self.samples.t_s) < 2:
            raise ValueError("the trajectory is shorter than one haptic step")
        self.state = make_state(model)
        self.consumer = TissueReplica(model, self.state, surface=True)
        cam = model.case.camera
        view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
        self.view = view / np.linalg.norm(view)
        side = np.cross(self.view, np.asarray(cam.up, float))   # the view's right
        self._side = side / np.linalg.norm(side)
        self.dust = DustGrid.for_grid(self.consumer.grid, gravity=self.view)
        self.scene = Scene.from_model(model, self.consumer.surface, offscreen=True,
                                      size=tuple(size))
        focal = np.asarray(cam.focal_mm, float)
        eye = focal + (np.asarray(cam.eye_mm, float) - focal) / ZOOM
        self.scene.set_case_camera(eye, focal, cam.up)
        self.injuries: list[str] = []
        self.q = 0                                   # next sample to step
        self.frame_hz = None                         # run_showcase: the video's rate
        self._force = np.zeros(len(self.samples.t_s))  # |force| per step [N]
        self.t_s = float(self.samples.t_s[0])
        self._dust_t_s = self.t_s                    # where the dust's last interval ended
        self.force_n = 0.0
        self.monitor = self.trace = None
        self._trace_due = False                      # monitor fed since the last show
        self.min_clearance_mm = math.inf
        self.min_clearance_label = 0               # the structure it was to
        if monitor:
            self._start_monitor()

    # ------------------------------------------------------------ monitor
    def _start_monitor(self) -> None:
        from bonesim.runtime.monitor import (HISTORY_CAP, SPIKE_CAP, NerveMonitor,
                                             monitored_structures)

        if not monitored_structures(self.model):
            return
        from bonesim.render.trace import MonitorTrace

        self.monitor = nm = NerveMonitor(self.model)
        k = nm.n
        self._hist = events.Ring.create(HISTORY_CAP, t_s=(np.float64, ()),
                                        rate=(np.float32, (k,)), dist=(np.float32, (k,)))
        self._spikes = events.Ring.create(SPIKE_CAP, t_s=(np.float64, ()),
                                          nerve=(np.uint8, ()))
        p = nm.params
        self.trace = MonitorTrace(self.scene, nm.names, nm.colors, max_hz=p.max_hz,
                                  warn_mm=p.warn_mm, baseline_hz=p.baseline_hz)

    def _feed_monitor(self, lo: int, hi: int) -> None:
        """Update the monitor from steps ``lo .. hi - 1`` in 20 ms chunks."""
        nm, s = self.monitor, self.samples
        t = s.t_s
        while lo < hi:
            stop = int(np.searchsorted(t, t[lo] + MONITOR_DT_S, side="left"))
            stop = min(max(stop, lo + 1), hi)
            sl = slice(lo, stop)
            nm.update_many(t[sl], s.pos_mm[sl], self._force[sl], s.drill[sl])
            st_t, st_n = nm.spikes
            self._spikes.append(t_s=st_t, nerve=st_n)
            self._hist.append(t_s=np.array([nm.t_s]),
                              rate=nm.rates_hz.reshape(1, -1).astype(np.float32),
                              dist=nm.distance_mm.reshape(1, -1).astype(np.float32))
            lo = stop

    # ------------------------------------------------------------ running
    @property
    def start_s(self) -> float:
        return float(self.samples.t_s[0])

    @property
    def end_s(self) -> float:
        return float(self.samples.t_s[-1])

    def _tip(self, q: int) -> tuple[bool, bool]:
        """(suction, irrigation) at sample ``q``."""
        s = self.samples
        return bool(s.suction[q]), bool(s.irrigation[q])

    def _assist(self, q: int):
        """Where suction and irrigation act at sample ``q`` [mm] (None: off).

        Rinses (drill off) follow the plan's columns at the suction tip;
        while the drill runs, the water lands at the burr and the suction
        tip trails it by :data:`ASSIST_LAG_S`."""
        s = self.samples
        if s.drill[q]:
            lag = int(np.searchsorted(s.t_s, s.t_s[q] - ASSIST_LAG_S, side="left"))
            return self._tip_mm(min(lag, q)), s.pos_mm[q]
        suck, wet = self._tip(q)
        tip = self._tip_mm(q) if (suck or wet) else None
        return (tip if suck else None), (tip if wet else None)

    def _tip_mm(self, q: int) -> np.ndarray:
        """Where the suction-irrigator's tip is at sample ``q`` [mm]: the
        front of the burr's sphere, the point the plan keeps
        ``rinse_gap_mm`` off the cavity (the trajectory gives the burr
        centre)."""
        s = self.samples
        a = np.asarray(s.axis[q], float)
        r = self.model.burrs[int(s.burr[q])].radius_mm
        return s.pos_mm[q] + r * a / np.linalg.norm(a)

    def advance(self, t_s: float) -> None:
        """Step the engine through every sample up to ``t_s`` and bring the
        surface, dust, monitor and scene to that moment.

        The same as :meth:`simulate`, :meth:`capture`, :meth:`step_dust` and
        :meth:`show` in turn; :func:`run_showcase` runs those stages of
        consecutive frames side by side (module docstring).

        Parameters
        ----------
        t_s : float
            Simulated time [s]; at most the trajectory's end.
        """
        self.simulate(t_s)
        frame = self.capture()
        self.step_dust(frame)
        self.show(frame)

    def simulate(self, t_s: float) -> None:
        """Step the engine through every sample up to ``t_s``; follow the
        burr's clearance and feed the nerve monitor to that moment.

        Parameters
        ----------
        t_s : float
            Simulated time [s]; at most the trajectory's end.
        """
        from bonesim.engine.model import Sample
        from bonesim.engine.world import world_step
        from bonesim.engine.world_commands import SetBurr

        s, model, state = self.samples, self.model, self.state
        t_s = min(float(t_s), self.end_s)
        hi = int(np.searchsorted(s.t_s, t_s, side="right"))
        lo = self.q
        none = ()
        for q in range(lo, hi):
            b = int(s.burr[q])                   # a change: the loop's SetBurr
            f = world_step(model, state, Sample(s.t_s[q], s.pos_mm[q], s.axis[q],
                                                bool(s.drill[q]), float(s.speed_rpm[q]),
                                                int(s.direction[q]), b),
                           none if b == state.burr else (SetBurr(b),))
            self._force[q] = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        self.q = max(hi, lo)
        self._clearance(lo, self.q)
        self.t_s = max(t_s, self.t_s)
        lo_f = max(lo - int(model.haptic_rate_hz * MONITOR_DT_S), 0)
        self.force_n = float(self._force[lo_f:self.q].max()) if self.q > lo_f else 0.0
        if self.monitor is not None and self.q > lo:
            self._feed_monitor(lo, self.q)
            self._trace_due = True

    def capture(self) -> "Frame":
        """What the dust and the picture need of the engine at the moment
        :meth:`simulate` reached, taken while the engine waits: the tissue
        events since the last capture, the touched voxels (their flags
        cleared, as a replica's drain does, so they are published again),
        a copy of the bone's densities, the HUD's figures and the monitor's
        history. Later stages read only the :class:`Frame`, so the engine
        may step on meanwhile."""
        from bonesim.engine.grid import Grid
        from bonesim.engine.model import clear_touched
        from bonesim.runtime.monitor import read_history

        st, c = self.state, self.consumer
        ev = c.cursor.drain()
        tch = c.touched.drain()["ijk"]
        if len(tch):
            clear_touched(st, tch)
        g = st.grid
        bone = Grid(g.spacing_mm, g.origin_mm, g.shape, g.keys, g.vals, g.bricks,
                    g.density.copy(), g.label)
        history = None
        if self._trace_due:
            self._trace_due = False
            history = read_history(self._hist, self._spikes, self.monitor.t_s,
                                   self.monitor.n, self.trace.window_s)
        frame = Frame(ev, tch, bone, max(self.q - 1, 0), self._dust_t_s, self.t_s,
                      self.force_n, history)
        self._dust_t_s = self.t_s
        return frame

    def step_dust(self, frame: "Frame") -> None:
        """Turn the frame's removals into dust and move the dust through the
        frame's interval in steps of at most :data:`DUST_DT_S`, each with
        the tool, suction and irrigation of its own moment; the walls are
        the bone the frame captured. Touches only the dust (it may run on
        another thread while the engine steps on)."""
        s = self.samples
        rem = events.removals(frame.events)["ijk"]
        if len(rem):
            self.dust.add_removed(rem)
        burr = self.model.burrs[int(s.burr[frame.q])]
        t0 = frame.t0_s
        dt = max(frame.t_s - t0, 0.0)
        n_sub = int(math.ceil(dt / DUST_DT_S)) if dt > 0 else 0
        for k in range(n_sub):
            qk = min(int(np.searchsorted(s.t_s, t0 + (k + 1) * dt / n_sub, side="right")) - 1,
                     len(s.t_s) - 1)
            qk = max(qk, 0)
            pk = s.pos_mm[qk]
            suck_at, wet_at = self._assist(qk)
            self.dust.step(frame.bone, dt / n_sub, tool_pos_mm=pk,
                           tool_radius_mm=burr.radius_mm,
                           suction_pos_mm=suck_at,
                           suction_radius_mm=TIP_RADIUS_MM if suck_at is not None else 0.0,
                           irrigation_pos_mm=wet_at,
                           irrigation_radius_mm=WATER_RADIUS_MM if wet_at is not None else 0.0)

    def show(self, frame: "Frame", sprites=None) -> None:
        """Bring the scene to the frame: its events into the replica's
        surface, then the dust's sprites (default: gathered now, after
        :meth:`step_dust` of this frame and before that of the next), the
        tools, the HUD and the monitor's trace. Call it only while no frame
        is being drawn."""
        from bonesim.physics.sightline import depth_below_surface_mm

        s, model = self.samples, self.model
        cur = frame.q
        ch = self.consumer.apply(frame.events, frame.touched, live=frame.bone)
        self.scene.update_bodies(self.consumer, ch.changed, ch.touched)   # bodies at their poses
        burr = model.burrs[int(s.burr[cur])]
        pos, axis = s.pos_mm[cur], s.axis[cur]
        suction, irrigation = self._tip(cur)
        self.scene.set_dust(*(self.dust.sprites() if sprites is None else sprites))
        tool = "suction" if suction else "irrigation" if irrigation else "burr"
        drill = bool(s.drill[cur])
        depth = None
        if tool == "burr":
            eye = self.scene.camera_pose()[0]
            depth = depth_below_surface_mm(self.consumer.grid, pos, eye, burr.radius_mm)
        if tool == "burr":
            self.scene.set_tool(pos, axis, burr.radius_mm, drill, depth_mm=depth)
            suck_at = self._assist(cur)[0] if drill else None
            self.scene.set_suction(suck_at, axis - SUCTION_TILT * self._side,
                                   SUCTION_DRAWN_RADIUS_MM)
        else:
            self.scene.set_suction(None)
            self.scene.set_tool(self._tip_mm(cur), axis, TIP_RADIUS_MM, False, kind="suction")
        for lab in ch.injuries["label"]:
            name = model.structure_name(int(lab))
            if name not in self.injuries:
                self.injuries.append(name)
        self.scene.set_hud({
            "case": model.name, "burr": burr.name, "burr_kind": burr.kind,
            "burr_diameter_mm": burr.diameter_mm, "tool": tool, "drill": drill,
            "direction": int(s.direction[cur]), "speed_rpm": float(s.speed_rpm[cur]),
            "force_n": frame.force_n, "haptic_hz": model.haptic_rate_hz,
            "frame_hz": self.frame_hz,
            "elapsed_s": frame.t_s - self.start_s, "injuries": list(self.injuries),
            **({} if depth is None else {"depth_mm": depth}),
            "message": "simulated time"})
        if frame.history is not None:
            self.trace.update(frame.history)

    def _clearance(self, lo: int, hi: int) -> None:
        """Track the running burr's closest approach to a structure that is not
        bone (every :data:`~bonesim.runtime.simulate.CLEARANCE_EVERY` th step; exact
        native-resolution distances, :func:`bonesim.runtime.simulate.closest_approach`)."""
        if hi <= lo:
            return
        s = self.samples
        sl = slice(lo - lo % -CLEARANCE_EVERY, hi, CLEARANCE_EVERY)
        on = s.drill[sl].astype(bool)
        radii = np.array([b.radius_mm for b in self.model.burrs])[s.burr[sl][on]]
        gap, label, _ = closest_approach(self.model, s.pos_mm[sl][on], radii)
        if gap < self.min_clearance_mm:
            self.min_clearance_mm, self.min_clearance_label = gap, label

    def image(self) -> np.ndarray:
        """The current frame, (height, width, 3) uint8."""
        return self.scene.image()

    def summary(self) -> dict:
        """What the run did so far (JSON-ready)."""
        st = self.state
        counts = st.removed_by_label
        return {
            "case": self.model.name, "burr": self.model.burr.name,
            "burrs": [b.name for b in self.model.burrs],
            "simulated_s": round(self.t_s - self.start_s, 3),
            # the tool path's length (with ``seconds``, of the part planned)
            "plan_s": round(self.end_s - self.start_s, 3),
            "steps": int(self.q),
            "voxels_removed": int(counts.sum()),
            "removed_by_structure": {self.model.structure_name(i): int(c)
                                     for i, c in enumerate(counts) if c and i},
            "injuries": list(self.injuries),
            "dust_cells": float(round(self.dust.total_cells, 2)),
            "dust_suctioned_cells": float(round(self.dust.suctioned_cells, 2)),
            **({} if not math.isfinite(self.min_clearance_mm) else
               {"min_clearance_mm": round(self.min_clearance_mm, 3),
                "min_clearance_structure": self.model.structure_name(
                    self.min_clearance_label)}),
        }

    def close(self) -> None:
        self.scene.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def run_showcase(case="phantom", burr="cutting-5mm", *, video="bonesim-run.mp4",
                 picture="bonesim-run.png", size=SIZE, video_s: float = VIDEO_S,
                 fps: float = VIDEO_FPS, monitor: bool = True, seconds: float | None = None,
                 trajectory=None, progress=None, assess=None) -> dict:
    """Drill the whole demo plan in simulated time; write a video and a picture.

    Parameters
    ----------
    case, burr
        As :class:`Showcase`.
    video : path or None
        The time-lapse video (``.mp4``); None: no video.
    picture : path or None
        The final frame (``.png``); None: none.
    size : (int, int)
        Frame size [px].
    video_s : float
        Video length [s]: the plan's duration is sped up to fit.
    fps : float
        Video frame rate [Hz].
    monitor : bool
        Show the nerve monitor's trace (when the case monitors a nerve).
    seconds : float, optional
        Drill only the plan's first ``seconds`` [s of simulated time].
    trajectory : bonesim.io.trajectory.Trajectory, optional
        Another tool path than the demo plan.
    progress : callable, optional
        Called as ``progress(done, total, what)`` after each frame.
    assess : callable, optional
        Called as ``assess(model, grid)`` with the tissue at the end; what it
        returns is the summary's ``assessment`` (``bonesim run`` passes the
        final-product assessment, :func:`bonesim.cli.assess.checklist_of_grid`).

    Returns
    -------
    dict
        :meth:`Showcase.summary` plus ``frames``, ``speedup``, ``wall_s``,
        the files written and (with ``assess``) ``assessment``.
    """
    from bonesim.session.video import VideoWriter

    wall0 = time.perf_counter()
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"seconds must be positive, got {seconds!r}")
    with Showcase(case, burr, size=size, monitor=monitor, trajectory=trajectory,
                  seconds=seconds) as show:
        n = max(2, int(round(video_s * fps)))
        show.frame_hz = fps
        end = show.end_s if seconds is None else min(show.end_s, show.start_s + seconds)
        times = np.linspace(show.start_s, end, n)
        writer = VideoWriter(video, size, fps) if video is not None else None
        try:
            advance_through(show, times, writer.write if writer is not None else None,
                            progress)
            if writer is not None:
                writer.close()
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
        out = show.summary()
        if assess is not None:
            out["assessment"] = assess(show.model, show.state.grid)
        out["frames"] = n
        out["speedup"] = round((end - show.start_s) / video_s, 2)
        if picture is not None:
            out["picture"] = str(show.scene.screenshot(picture))
        if video is not None:
            out["video"] = str(video)
    out["wall_s"] = round(time.perf_counter() - wall0, 2)
    return out


def advance_through(show: Showcase, times, sink=None, progress=None) -> None:
    """Advance ``show`` to each of ``times`` [s of simulated time], drawing
    each frame into ``sink(image)`` (None: draw nothing; the scene still
    follows), with the stages of three consecutive
    frames side by side: the engine steps frame ``i + 1`` on this thread
    while a worker moves the dust of frame ``i`` and another draws frame
    ``i - 1`` (:mod:`bonesim.apps.frames`). Each stage reads what the stage
    before captured for its frame, in the order :meth:`Showcase.advance`
    runs them, so the frames are the same as advancing in line."""
    from bonesim.apps.frames import FrameWorker, Worker

    dust = Worker("bonesim-dust")
    draw = FrameWorker(show.scene, sink) if sink is not None else None
    n = len(times)
    try:
        pending = None                      # the frame whose dust is moving
        for i, t in enumerate(times):
            show.simulate(t)
            frame = show.capture()
            dust.wait()
            sprites = show.dust.sprites() if pending is not None else None
            dust.submit(lambda f=frame: show.step_dust(f))
            if pending is not None:
                _draw(show, pending, sprites, draw, progress, i, n)
            pending = frame
        dust.wait()
        _draw(show, pending, show.dust.sprites(), draw, progress, n, n)
        if draw is not None:
            draw.wait()
    finally:
        dust.close()
        if draw is not None:
            draw.close()


def _draw(show, frame, sprites, draw, progress, done, n) -> None:
    if draw is not None:
        draw.wait()
    show.show(frame, sprites)
    if draw is not None:
        draw.submit()
    if progress is not None:
        progress(done, n, "drilling the plan")
