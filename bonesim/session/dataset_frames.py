"""What each frame of a dataset shows, as data (no VTK): the tissue, the
tool, the dust, the water, the suction tool and the cameras at each frame
time.

The tissue and the tool are playback's (:class:`bonesim.session.playback.Player`).
A recording holds no dust and no suction-tip pose, so :class:`FrameSource`
simulates the dust and the water again from the recording
(:class:`bonesim.physics.dust.DustGrid`): every recorded removal becomes
dust when it happens, and the dust moves on a fixed clock of
:data:`DUST_DT_S` steps from the recording's start, whatever the frame rate,
with the burr at its recorded pose pushing it, and its sprites (whose age
fades them) listed at every step, so the dust of a moment is the same in
every dataset of the run. Water: where the recording's key
events turned irrigation on, at the burr (as the window pours it); with
``suction="follow"`` also the suction-irrigator of the headless main job
(:mod:`bonesim.apps.showcase`: while the drill runs, water lands at the burr
and the suction tip trails the burr along its path by
:data:`ASSIST_LAG_S`, taking up dust and water). Everything is integer or
fixed-order arithmetic: the same recording and options give the same
frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bonesim.session.dataset_camera import frame_camera, stereo_cameras
from bonesim.session.dataset_spec import ORBIT_HALF_ANGLE_DEG, ORBIT_PERIOD_S, DatasetOptions
from bonesim.session.playback import Frame, Player
from bonesim.session.video import video_times

__all__ = ["DUST_DT_S", "ASSIST_LAG_S", "SUCTION_TIP_RADIUS_MM", "ASSIST_WATER_RADIUS_MM",
           "KEY_WATER_SPREAD_MM", "SUCTION_DRAWN_RADIUS_MM", "SUCTION_TILT", "FrameState",
           "FrameSource", "irrigation_switches"]

#: The dust's fixed step [s of recording time].
DUST_DT_S = 1.0 / 30.0
# The suction-irrigator of the headless main job (bonesim.apps.showcase's
# ASSIST_LAG_S, TIP_RADIUS_MM, WATER_RADIUS_MM, SUCTION_DRAWN_RADIUS_MM,
# SUCTION_TILT; the session layer cannot import the apps):
#: How far the suction tip trails the burr along its path [s].
ASSIST_LAG_S = 0.5
#: Radius within which the suction tip takes up dust and water [mm].
SUCTION_TIP_RADIUS_MM = 1.5
#: Radius of the patch the irrigation wets around the burr [mm].
ASSIST_WATER_RADIUS_MM = 4.0
#: How far past the burr's surface the window's irrigation wets [mm]
#: (bonesim.apps.simulator.WATER_SPREAD_MM).
KEY_WATER_SPREAD_MM = 2.0
#: The drawn suction tube's radius [mm] and its tilt from the drill axis
#: across the view [tan of the angle].
SUCTION_DRAWN_RADIUS_MM = 1.1
SUCTION_TILT = 0.3


@dataclass
class FrameState:
    """Everything one dataset frame shows, as data.

    Attributes
    ----------
    frame : bonesim.session.playback.Frame
        Tool, drill, burr, force, removed voxels at the frame's time.
    cameras : list of (eye, focal, up)
        One per eye [mm] (left first), before rendering.
    dust, water : DustSprites or None
        Sprites to draw (``positions, density, cell_mm, age_s, wet``).
    suction : tuple or None
        ``(tip_mm, axis, radius_mm)`` of the drawn suction tool.
    irrigation : bool
        Water flows at this moment.
    """

    frame: Frame
    cameras: list
    dust: object = None
    water: object = None
    suction: tuple | None = None
    irrigation: bool = False


def irrigation_switches(session) -> np.ndarray:
    """Session times [s] at which the recording's key events toggled
    irrigation (``key`` / ``irrigation``), sorted."""
    out = []
    for ev in getattr(session, "events", None) or []:
        try:
            t, name, value = ev
        except (TypeError, ValueError):
            continue
        name = name.decode() if isinstance(name, bytes) else str(name)
        value = value.decode() if isinstance(value, bytes) else str(value)
        if name == "key" and value == "irrigation" and t == t:
            out.append(float(t))
    return np.sort(np.asarray(out, np.float64))


class FrameSource:
    """The frames of a dataset of one recording, in time order.

    Parameters
    ----------
    session : Session
        As :func:`bonesim.session.reader.read_session` returns it.
    options : DatasetOptions
    player : Player, optional
        Default: a new one (with a surface) over ``session``.

    Attributes
    ----------
    player : Player
    times : (n,) float64
        Playback times of the frames [s].
    """

    def __init__(self, session, options: DatasetOptions, player: Player | None = None):
        self.session = session
        self.options = options
        self.player = Player(session) if player is None else player
        tl = self.player.timeline
        self.times = video_times(tl.duration, options.fps, 1.0, options.start, options.end)
        model = self.player.model
        case = getattr(model, "case", None)
        cam = getattr(case, "camera", None)
        if cam is None:                             # a stand-in model without a case
            from types import SimpleNamespace

            g = model.grid
            centre = g.origin_mm + 0.5 * g.spacing_mm * (np.asarray(g.shape) - 1)
            cam = SimpleNamespace(eye_mm=tuple(centre + [0.0, 0.0, 100.0]),
                                  focal_mm=tuple(centre), up=(0.0, 1.0, 0.0))
        self.case_camera = cam
        view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
        self._view = view / np.linalg.norm(view)
        side = np.cross(self._view, np.asarray(cam.up, float))
        self._side = side / np.linalg.norm(side)
        gravity = getattr(case, "gravity_dir", None)
        self._gravity = np.asarray(gravity if gravity is not None else self._view, float)
        self._switch = irrigation_switches(session) - tl.t0
        # the dust's own copy of the tissue, without a surface: stepping the dust
        # every DUST_DT_S never re-tessellates (only the frames' player does)
        self._walls = Player(session, self.player.model, self.player.burrs, surface=False)
        self._tick = 0                     # dust steps done
        self._dust = None
        self._epoch = None
        self._rem_hi = 0
        self._last_t = -math.inf

    # ---------------------------------------------------------------- tool
    def _sample(self, t: float) -> int:
        return self.player.timeline.sample_index(t)

    def _radius(self, q: int) -> float:
        b = self.player.burrs[int(self.player.timeline.samples["burr"][q])]
        return float(getattr(b, "radius_mm", 1.0))

    def _tip_mm(self, q: int) -> np.ndarray:
        """Front of the burr's sphere at sample ``q`` (the suction tip's place
        in the headless job) [mm]."""
        s = self.player.timeline.samples
        a = np.asarray(s["axis"][q], float)
        n = np.linalg.norm(a)
        return s["pos_mm"][q] + (self._radius(q) * a / n if n > 0 else 0.0)

    def irrigating(self, t: float) -> bool:
        """Irrigation on at playback time ``t`` by the recorded key events."""
        return bool(np.searchsorted(self._switch, t, side="right") % 2)

    def _assist(self, t: float):
        """``(suction tip or None, water centre or None, water radius)`` at ``t``."""
        q = self._sample(t)
        s = self.player.timeline.samples
        pos = s["pos_mm"][q]
        suck, wet, radius = None, None, 0.0
        if self.options.suction == "follow" and s["drill"][q]:
            lag = int(np.searchsorted(s["t_s"], s["t_s"][q] - ASSIST_LAG_S, side="left"))
            suck = self._tip_mm(min(lag, q))
            wet, radius = pos, ASSIST_WATER_RADIUS_MM
        if self.irrigating(t):
            wet = pos
            radius = max(radius, self._radius(q) + KEY_WATER_SPREAD_MM)
        return suck, wet, radius

    # ---------------------------------------------------------------- dust
    def _new_dust(self):
        from bonesim.physics.dust.grid import DustGrid

        return DustGrid.for_grid(self._walls.grid, gravity=self._gravity)

    def _dust_step(self, tau: float) -> None:
        """Bring the dust to tick time ``tau``: the removals up to it, then one
        step of :data:`DUST_DT_S` with the tool of that moment."""
        from bonesim.engine.bodies import all_identity, voxel_bodies

        p = self._walls
        p.seek(tau)
        tl = p.timeline
        epoch, lo, hi = tl.removal_range(tau)
        if epoch != self._epoch or self._dust is None:
            self._dust, self._epoch, self._rem_hi = self._new_dust(), epoch, lo
        new = tl.rem_ijk[max(self._rem_hi, lo):hi]
        self._rem_hi = max(self._rem_hi, hi)
        st = p.replica.state
        if len(new):
            ident = all_identity(st)
            self._dust.add_removed(new, body=None if ident else
                                   voxel_bodies(p.grid, st.body, new), bodies=st)
        q = self._sample(tau)
        suck, wet, radius = self._assist(tau)
        self._dust.step(p.grid, DUST_DT_S, tool_pos_mm=tl.samples["pos_mm"][q],
                        tool_radius_mm=self._radius(q), suction_pos_mm=suck,
                        suction_radius_mm=SUCTION_TIP_RADIUS_MM if suck is not None else 0.0,
                        irrigation_pos_mm=wet, irrigation_radius_mm=radius, bodies=st)
        # note when each cell's dust arrived (its age fades it) at every step, so
        # that ages do not depend on the frame rate
        self._dust.note_arrivals()

    def at(self, t: float) -> FrameState:
        """The frame at playback time ``t`` (times must not decrease from call
        to call: the dust only goes forward)."""
        from bonesim.physics.dust.water import water_sprites

        t = float(t)
        if t < self._last_t:
            raise ValueError("frames must be asked for in time order")
        self._last_t = t
        while (self._tick + 1) * DUST_DT_S <= t + 1e-9:
            self._tick += 1
            self._dust_step(self._tick * DUST_DT_S)
        p = self.player
        p.seek(t)
        f = p.frame()
        if self._dust is None or p.timeline.epoch_at(t) != self._epoch:
            self._dust, self._epoch = self._new_dust(), p.timeline.epoch_at(t)
            self._rem_hi = p.timeline.removal_range(t)[1]
        dust = self._dust.sprites()
        water = water_sprites(self._dust) if self._dust.water is not None else None
        suck, _, _ = self._assist(t)
        suction = None
        if suck is not None:
            suction = (suck, f.axis - SUCTION_TILT * self._side, SUCTION_DRAWN_RADIUS_MM)
        o = self.options
        eye, focal, up = frame_camera(o.camera, t, f.camera, self.case_camera, o.zoom,
                                      (ORBIT_HALF_ANGLE_DEG, ORBIT_PERIOD_S))
        return FrameState(f, stereo_cameras(eye, focal, up, o.stereo_mm), dust, water,
                          suction, self.irrigating(t))

    def __iter__(self):
        for t in self.times:
            yield self.at(float(t))
