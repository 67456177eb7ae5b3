"""Playback of a recorded session: the tissue, tool and events at any time.

This module holds everything about playback that does not draw: it is used
by the playback window and the video export (:mod:`bonesim.render.playback`)
and is tested without VTK.

Time
----
Playback time ``t`` [s] runs from 0 (the recording's first haptic sample) to
:attr:`Timeline.duration` (its last sample). Session times (seconds since the
haptic loop started, as stored in the file) are ``timeline.t0 + t``.

What is shown at time ``t``
---------------------------
* Tool, drill, burr, force: the last haptic sample at or before ``t``.
* Tissue: the case's initial grid with every recorded tissue event of the
  current epoch (the samples' ``epoch`` at ``t``; a case reset starts a new
  epoch with the initial tissue) made at or before ``t`` applied: removals,
  body splits and poses. The file records removals only, not the partial density loss of voxels that
  were grazed, so a partly drilled voxel is shown intact (same geometry as
  the live run; only its shading can differ).
* Injuries: the injuries recorded at or before ``t`` in the current epoch
  (listed as structure names, as the live HUD does), and a notice for
  :data:`INJURY_NOTICE_S` seconds after each one (until a reset).
* Camera: the recorded camera stream interpolated linearly at ``t``, if the
  session has one.

:class:`Player` keeps the tissue and its :class:`~bonesim.engine.surface.Surface`
at the current time in a :class:`~bonesim.engine.replica.TissueReplica`: a forward
seek applies the events in between and updates the surface incrementally;
a backward seek, or a seek across a reset, starts again from the initial
tissue and tessellates once.

Session objects
---------------
Anything with the attributes of :func:`bonesim.session.reader.read_session`'s
result works: ``header``, ``complete``, ``samples``, ``tissue`` (or, for a
stand-in, ``removals`` alone), ``removals``, ``injuries``, ``camera``,
``events``, ``load_model()`` and ``burr_models()``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.io.anatomy import clinical_name
from bonesim.progress import format_clock
from bonesim.engine.replica import TissueReplica

__all__ = ["SPEEDS", "INJURY_NOTICE_S", "SEEK_SHORT_S", "SEEK_LONG_S", "Timeline",
           "Frame", "Player", "hud_info", "handle_text", "PlaybackClock"]

#: Playback speeds offered by :meth:`PlaybackClock.faster` / ``slower``.
SPEEDS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: How long the HUD names an injury after it happened [s of session time].
INJURY_NOTICE_S = 2.0
#: Short and long seek steps of the arrow keys [s].
SEEK_SHORT_S = 1.0
SEEK_LONG_S = 10.0

_EMPTY_IJK = np.zeros((0, 3), dtype=np.int32)


def _where(session):
    """The session's file, for error messages (None if unknown)."""
    p = getattr(session, "path", None)
    return None if p is None else Path(p)


def _column(session, group: str, name: str, n_rows: int | None, shape=(), dtype=None):
    """One column of a session table, checked for its row count and shape."""
    table = getattr(session, group, None)
    if table is None or name not in table:
        raise BonesimError(f"session has no {group} column {name!r}", _where(session),
                           f"{group}/{name}")
    a = np.asarray(table[name])
    if dtype is not None:
        a = a.astype(dtype, copy=False)
    want = ((a.shape[0] if n_rows is None else n_rows),) + tuple(shape)
    if a.shape != want:
        raise BonesimError(f"expected shape {want}, got {a.shape}", _where(session),
                           f"{group}/{name}")
    return a


# ---------------------------------------------------------------- timeline
class Timeline:
    """Time index of a recorded session (read-only lookups by playback time).

    Parameters
    ----------
    session : Session
        See the module docstring.

    Attributes
    ----------
    t0, t1 : float
        Session times of the first and last haptic sample [s].
    duration : float
        ``t1 - t0`` [s].
    samples : dict of ndarray
        The session's per-step columns (``t_s`` in session time).
    rem_t, rem_ijk, rem_epoch, rem_label : ndarray
        Removals sorted by time: session time [s], voxel, epoch, label.
    inj_t, inj_label, inj_kind, inj_epoch : ndarray
        Injuries sorted by time (``inj_t`` in playback time [s]) with the
        epoch in which each happened.
    reset_t : ndarray
        Playback times of the case resets [s].
    cam_t, cam_eye, cam_focal, cam_up : ndarray
        Camera stream (``cam_t`` in session time [s]); empty if none.
    """

    def __init__(self, session):
        self.session = session
        where = _where(session)
        t = _column(session, "samples", "t_s", None, dtype=np.float64)
        n = t.shape[0]
        if n == 0:
            raise BonesimError("the session has no haptic samples: nothing to play back",
                               where, "samples/t_s")
        if not np.isfinite(t).all() or (np.diff(t) < 0).any():
            raise BonesimError("sample times must be finite and non-decreasing", where,
                               "samples/t_s")
        cols = {"t_s": t}
        for name, shape, dt in (("pos_mm", (3,), np.float64), ("axis", (3,), np.float64),
                                ("drill", (), np.uint8), ("speed_rpm", (), np.float64),
                                ("direction", (), np.int8), ("burr", (), np.int64),
                                ("epoch", (), np.int64), ("force_n", (3,), np.float64)):
            cols[name] = _column(session, "samples", name, n, shape, dt)
        if (np.diff(cols["epoch"]) < 0).any():
            raise BonesimError("the epoch (case reset count) decreases", where,
                               "samples/epoch")
        self.samples = cols
        self.t0 = float(t[0])
        self.t1 = float(t[-1])
        self.duration = self.t1 - self.t0

        rt = _column(session, "removals", "t_s", None, dtype=np.float64)
        m = rt.shape[0]
        ijk = _column(session, "removals", "ijk", m, (3,), np.int32)
        rep = _column(session, "removals", "epoch", m, (), np.int64)
        lab = _column(session, "removals", "label", m, (), np.uint8)
        if m and (np.diff(rt) < 0).any():
            order = np.argsort(rt, kind="stable")
            rt, ijk, rep, lab = rt[order], ijk[order], rep[order], lab[order]
        if m and (np.diff(rep) < 0).any():
            raise BonesimError("removals: the epoch decreases over time", where,
                               "removals/epoch")
        self.rem_t = rt
        self.rem_ijk = np.ascontiguousarray(ijk)
        self.rem_epoch = rep
        self.rem_label = lab

        it = _column(session, "injuries", "t_s", None, dtype=np.float64)
        k = it.shape[0]
        ilab = _column(session, "injuries", "label", k, (), np.int64)
        ikind = _column(session, "injuries", "kind", k, (), np.int64)
        order = np.argsort(it, kind="stable")
        self.inj_t = it[order] - self.t0
        self.inj_label = ilab[order]
        self.inj_kind = ikind[order]
        self.inj_epoch = self._epoch_of(it[order])

        # what shapes the tissue (removals, splits, poses), for the replica
        tissue = getattr(session, "tissue", None)
        if tissue is None:                 # removals alone (a stand-in session)
            ev = events.empty_events(m)
            ev["kind"][:] = events.REMOVED
            ev["t_s"][:], ev["ijk"][:], ev["label"][:] = rt, self.rem_ijk, lab
        else:
            ev = events.select({f: tissue[f] for f in events.TISSUE_FIELDS},
                               events.REMOVED, events.SPLIT, events.POSE, events.PLATE)
            order = np.argsort(ev["t_s"], kind="stable")
            ev = {f: a[order] for f, a in ev.items()}
        self.shape_ev = ev
        self.shape_epoch = self._epoch_of(ev["t_s"]) if tissue is not None else rep

        ep = cols["epoch"]
        self.reset_t = t[1:][np.diff(ep) > 0] - self.t0

        cam = getattr(session, "camera", None) or {}
        if len(cam) and "t_s" in cam and len(cam["t_s"]):
            ct = _column(session, "camera", "t_s", None, dtype=np.float64)
            c = ct.shape[0]
            eye = _column(session, "camera", "eye_mm", c, (3,), np.float64)
            foc = _column(session, "camera", "focal_mm", c, (3,), np.float64)
            up = _column(session, "camera", "up", c, (3,), np.float64)
            order = np.argsort(ct, kind="stable")
            self.cam_t, self.cam_eye = ct[order], eye[order]
            self.cam_focal, self.cam_up = foc[order], up[order]
        else:
            self.cam_t = np.zeros(0)
            self.cam_eye = self.cam_focal = self.cam_up = np.zeros((0, 3))

    # ------------------------------------------------------------- lookups
    def clamp(self, t: float) -> float:
        """``t`` limited to ``[0, duration]`` [s]."""
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"playback time must be finite, got {t}")
        return min(max(t, 0.0), self.duration)

    def sample_index(self, t: float) -> int:
        """Index of the last haptic sample at or before playback time ``t``."""
        T = self.t0 + self.clamp(t)
        return max(int(np.searchsorted(self.samples["t_s"], T, side="right")) - 1, 0)

    def _epoch_of(self, session_t) -> np.ndarray:
        idx = np.searchsorted(self.samples["t_s"], session_t, side="right") - 1
        return self.samples["epoch"][np.clip(idx, 0, None)]

    def epoch_at(self, t: float) -> int:
        """Case resets made at or before playback time ``t``."""
        return int(self.samples["epoch"][self.sample_index(t)])

    def removal_range(self, t: float) -> tuple[int, int, int]:
        """The removals that shape the tissue at playback time ``t``.

        Returns
        -------
        epoch, lo, hi : int
            Removals ``lo .. hi-1`` (of :attr:`rem_ijk`) are those of
            ``epoch`` made at or before ``t``.
        """
        t = self.clamp(t)
        e = self.epoch_at(t)
        lo = int(np.searchsorted(self.rem_epoch, e, side="left"))
        hi_e = int(np.searchsorted(self.rem_epoch, e, side="right"))
        hi = int(np.searchsorted(self.rem_t, self.t0 + t, side="right"))
        return e, lo, max(lo, min(hi, hi_e))

    def shape_range(self, t: float) -> tuple[int, int, int]:
        """The tissue events (removals, splits, poses) that shape the tissue at
        playback time ``t``: ``epoch, lo, hi`` with events ``lo .. hi-1`` of
        :attr:`shape_ev` those of ``epoch`` made at or before ``t``."""
        t = self.clamp(t)
        e = self.epoch_at(t)
        lo = int(np.searchsorted(self.shape_epoch, e, side="left"))
        hi_e = int(np.searchsorted(self.shape_epoch, e, side="right"))
        hi = int(np.searchsorted(self.shape_ev["t_s"], self.t0 + t, side="right"))
        return e, lo, max(lo, min(hi, hi_e))

    def camera_at(self, t: float):
        """Recorded camera at playback time ``t``: ``(eye_mm, focal_mm, up)``
        interpolated linearly between stream samples, or None without a stream."""
        n = self.cam_t.shape[0]
        if n == 0:
            return None
        T = self.t0 + self.clamp(t)
        i = int(np.searchsorted(self.cam_t, T, side="right")) - 1
        if i < 0:
            i, w = 0, 0.0
        elif i >= n - 1:
            i, w = n - 1, 0.0
        else:
            span = self.cam_t[i + 1] - self.cam_t[i]
            w = float((T - self.cam_t[i]) / span) if span > 0 else 0.0
        j = min(i + 1, n - 1)

        def lerp(a):
            return (1.0 - w) * a[i] + w * a[j]

        up = lerp(self.cam_up)
        nu = np.linalg.norm(up)
        up = up / nu if nu > 0 else self.cam_up[i]
        return lerp(self.cam_eye), lerp(self.cam_focal), up

    def injuries_until(self, t: float, epoch: int | None = None) -> np.ndarray:
        """Indices (into ``inj_*``) of the injuries at or before ``t``
        (of one ``epoch`` only, if given)."""
        n = int(np.searchsorted(self.inj_t, self.clamp(t), side="right"))
        idx = np.arange(n)
        if epoch is not None:
            idx = idx[self.inj_epoch[:n] == epoch]
        return idx


# -------------------------------------------------------------------- frames
@dataclass
class Frame:
    """What playback shows at one time.

    Attributes
    ----------
    t_s, duration_s : float
        Playback time and recording length [s].
    index : int
        Haptic sample shown.
    pos_mm, axis : (3,) float64
        Burr centre [mm] and drill axis (handle toward tip).
    drill : bool
    speed_rpm : float
    direction : int
        +1 forward, -1 reverse.
    burr_index : int
        Index into the session's burrs.
    burr : object
        That burr (``name``, ``radius_mm``, maybe ``kind``, ``diameter_mm``).
    force_n : float
        Magnitude of the force sent to the device [N].
    epoch : int
        Case resets so far.
    voxels_removed : int
        Voxels removed in this epoch up to ``t``.
    volume_removed_mm3 : float
        Their volume [mm^3].
    injuries : list of str
        Structures injured in this epoch up to ``t`` (each once, in order).
    recent : list of str
        Injuries of this epoch in the last :data:`INJURY_NOTICE_S` seconds,
        as ``"<structure> (<kind>) at <time>"``, the structure by its clinical
        name (:func:`bonesim.io.anatomy.clinical_name`).
    camera : tuple or None
        ``(eye_mm, focal_mm, up)`` of the recorded camera.
    handle_deg : tuple of float or None
        An instrumented handle's angles [deg] last recorded at or before the
        sample (``session.handle``, channels with an angle); None without.
    """

    t_s: float
    duration_s: float
    index: int
    pos_mm: np.ndarray
    axis: np.ndarray
    drill: bool
    speed_rpm: float
    direction: int
    burr_index: int
    burr: object
    force_n: float
    epoch: int
    voxels_removed: int
    volume_removed_mm3: float
    injuries: list = field(default_factory=list)
    recent: list = field(default_factory=list)
    camera: tuple | None = None
    handle_deg: tuple | None = None


def _handle_at(session, t_s: float):
    """The handle's angles [deg] last recorded at or before ``t_s`` (absolute
    loop time), without the NaN channels; None if there are none."""
    h = getattr(session, "handle", None)
    if h is None or not len(h["t_s"]):
        return None
    q = int(np.searchsorted(h["t_s"], t_s, side="right")) - 1
    if q < 0:
        return None
    a = tuple(float(x) for x in h["angles_deg"][q] if x == x)
    return a or None


class Player:
    """The tissue, its surface and the tool of a session at a movable time.

    Parameters
    ----------
    session : Session
        See the module docstring.
    model : Model, optional
        The recorded case (default: burr 0's model of
        ``session.burr_models()``, which checks the recorded hashes).
    burrs : list, optional
        Burr objects by session burr index (default: those of
        ``session.burr_models()``).
    surface : bool
        Keep a :class:`~bonesim.engine.surface.Surface` in step with the grid.

    Attributes
    ----------
    timeline : Timeline
    model : Model
    replica : TissueReplica
        The tissue at :attr:`t`, kept by applying the recorded tissue events.
    grid : Grid
        The replica's grid (a copy sharing the model's brick table).
    surface : Surface or None
        Its surface; replaced by a new object when a seek rebuilds.
    t : float
        Current playback time [s].
    stats : dict
        ``rebuilds``, ``forward`` (incremental seeks), ``applied`` (removals
        zeroed in all).
    """

    def __init__(self, session, model=None, burrs=None, *, surface: bool = True):
        self.session = session
        self.timeline = Timeline(session)
        if model is None or burrs is None:
            models = session.burr_models()          # one load for all burrs
            model = models[0] if model is None else model
            burrs = [m.burr for m in models] if burrs is None else burrs
        self.model = model
        self.burrs = list(burrs)
        if not self.burrs:
            self.burrs = [self.model.burr]
        used = int(self.timeline.samples["burr"].max())
        if used >= len(self.burrs) or int(self.timeline.samples["burr"].min()) < 0:
            raise BonesimError(f"samples use burr index {used} but the session lists "
                               f"{len(self.burrs)} burr(s)", _where(session), "samples/burr")
        if self.model.grid.label.size:
            top = int(self.model.grid.label.max())
            if self.timeline.rem_label.size and int(self.timeline.rem_label.max()) > top:
                raise BonesimError("removals name a structure label the case does not have",
                                   _where(session), "removals/label")
        self.stats = {"rebuilds": 0, "forward": 0, "applied": 0}
        self.replica = TissueReplica(self.model, surface=surface)
        self._epoch = None
        self._hi = 0
        self.t = 0.0
        self._rebuild(*self.timeline.shape_range(0.0))

    @property
    def grid(self):
        return self.replica.grid

    @property
    def surface(self):
        return self.replica.surface

    # --------------------------------------------------------------- seeking
    def _apply(self, lo: int, hi: int, surface: bool = True) -> np.ndarray:
        ev = self.timeline.shape_ev
        ch = self.replica.apply({f: a[lo:hi] for f, a in ev.items()}, surface=surface)
        self.stats["applied"] += len(ch.removed)
        return ch.changed                     # removed, and split off to other bodies

    def _rebuild(self, epoch: int, lo: int, hi: int) -> None:
        self.replica.reset(epoch, surface=False)
        self._apply(lo, hi, surface=False)
        self.replica.rebuild_surface()
        self._epoch, self._hi = epoch, hi
        self.stats["rebuilds"] += 1

    def seek(self, t: float) -> dict:
        """Bring the grid (and surface) to playback time ``t`` (clamped).

        Returns
        -------
        dict
            ``mode``: ``"none"`` (nothing changed), ``"forward"`` (removals
            applied incrementally) or ``"rebuild"`` (new grid and surface);
            ``removed``: (n, 3) int32 voxels a forward seek took out of a
            body's surface (removed, or split off to another body; pass them
            to ``Scene.update_bodies``); ``t``.
        """
        t = self.timeline.clamp(t)
        epoch, lo, hi = self.timeline.shape_range(t)
        self.t = t
        if epoch == self._epoch and hi == self._hi:
            return {"mode": "none", "removed": _EMPTY_IJK, "t": t}
        if epoch == self._epoch and hi > self._hi:
            ijk = self._apply(self._hi, hi)
            self._hi = hi
            self.stats["forward"] += 1
            return {"mode": "forward", "removed": ijk, "t": t}
        self._rebuild(epoch, lo, hi)
        return {"mode": "rebuild", "removed": _EMPTY_IJK, "t": t}

    # ---------------------------------------------------------------- frames
    def frame(self, t: float | None = None) -> Frame:
        """What is shown at ``t`` (default: the current time; does not seek)."""
        tl = self.timeline
        t = self.t if t is None else tl.clamp(t)
        i = tl.sample_index(t)
        s = tl.samples
        epoch, lo, hi = tl.removal_range(t)
        names = []
        for q in tl.injuries_until(t, epoch):
            name = self.model.structure_name(int(tl.inj_label[q]))
            if name not in names:
                names.append(name)
        recent = []
        for q in tl.injuries_until(t, epoch):
            if t - tl.inj_t[q] <= INJURY_NOTICE_S:
                kind = int(tl.inj_kind[q])
                name = clinical_name(self.model.structure_name(int(tl.inj_label[q])))
                recent.append(f"{name} ({'removal' if kind == 1 else 'contact'}) at "
                              f"{format_clock(tl.inj_t[q])}")
        b = int(s["burr"][i])
        return Frame(t_s=t, duration_s=tl.duration, index=i,
                     pos_mm=s["pos_mm"][i].copy(), axis=s["axis"][i].copy(),
                     drill=bool(s["drill"][i]), speed_rpm=float(s["speed_rpm"][i]),
                     direction=-1 if s["direction"][i] < 0 else 1, burr_index=b,
                     burr=self.burrs[b], force_n=float(np.linalg.norm(s["force_n"][i])),
                     epoch=epoch, voxels_removed=hi - lo,
                     volume_removed_mm3=(hi - lo) * self.model.spacing_mm ** 3,
                     injuries=names, recent=recent, camera=tl.camera_at(t),
                     handle_deg=_handle_at(self.session, float(s["t_s"][i])))


def hud_info(frame: Frame, model, *, speed: float | None = None,
             playing: bool | None = None, notices=()) -> dict:
    """The HUD dictionary (see :mod:`bonesim.render.hud`) of a playback frame.

    Parameters
    ----------
    frame : Frame
    model : Model
        For the case name.
    speed : float, optional
        Playback speed factor, shown with ``playing``.
    playing : bool, optional
    notices : sequence of str
        Extra lines (e.g. an incomplete recording).
    """
    b = frame.burr
    info = {"case": model.name, "burr": getattr(b, "name", "?")}
    if hasattr(b, "kind"):
        info["burr_kind"] = b.kind
    if hasattr(b, "diameter_mm"):
        info["burr_diameter_mm"] = b.diameter_mm
    info.update({"drill": frame.drill, "direction": frame.direction,
                 "speed_rpm": frame.speed_rpm, "force_n": frame.force_n,
                 "injuries": list(frame.injuries)})
    info["time"] = f"{format_clock(frame.t_s)} / {format_clock(frame.duration_s)}"
    if speed is not None:
        state = "" if playing is None else ("  playing" if playing else "  paused")
        info["playback"] = f"{speed:g}x{state}"
    removed = f"{frame.voxels_removed:,} voxels ({frame.volume_removed_mm3:.2f} mm^3)"
    if frame.epoch:
        removed += f" since reset {frame.epoch}"
    info["removed"] = removed
    if frame.handle_deg is not None:
        info["handle"] = handle_text(frame.handle_deg)
    lines = [f"INJURY {r}" for r in frame.recent] + [str(n) for n in notices]
    if lines:
        info["message"] = "\n".join(lines)
    return info


def handle_text(angles_deg) -> str | None:
    """The HUD's ``handle`` line: the angles with a value [deg], e.g.
    ``"7.5 / 90.0 deg"``; None if none has one."""
    a = [float(x) for x in angles_deg if x == x]
    return " / ".join(f"{x:.1f}" for x in a) + " deg" if a else None


# --------------------------------------------------------------------- clock
class PlaybackClock:
    """Play/pause, speed and seeking over ``[0, duration]``.

    Parameters
    ----------
    duration : float
        Recording length [s].
    t : float
        Start time [s].
    speed : float
        Start speed factor (one of :data:`SPEEDS` or any positive value).
    playing : bool
    """

    def __init__(self, duration: float, t: float = 0.0, speed: float = 1.0,
                 playing: bool = False):
        if not duration >= 0:
            raise ValueError(f"duration must be >= 0, got {duration}")
        if not speed > 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.duration = float(duration)
        self.speed = float(speed)
        self.playing = bool(playing)
        self.t = 0.0
        self.seek(t)

    def seek(self, t: float) -> float:
        """Jump to ``t`` (clamped to the recording) [s]; returns the new time."""
        self.t = min(max(float(t), 0.0), self.duration)
        return self.t

    def skip(self, dt: float) -> float:
        """Jump by ``dt`` seconds (negative: back)."""
        return self.seek(self.t + dt)

    def toggle(self) -> bool:
        """Play or pause; playing at the end starts again from 0."""
        if not self.playing and self.t >= self.duration:
            self.t = 0.0
        self.playing = not self.playing
        return self.playing

    def faster(self) -> float:
        """Next speed of :data:`SPEEDS` (stays at the fastest)."""
        up = [s for s in SPEEDS if s > self.speed * (1 + 1e-9)]
        self.speed = up[0] if up else self.speed
        return self.speed

    def slower(self) -> float:
        """Previous speed of :data:`SPEEDS` (stays at the slowest)."""
        down = [s for s in SPEEDS if s < self.speed * (1 - 1e-9)]
        self.speed = down[-1] if down else self.speed
        return self.speed

    def advance(self, wall_dt: float) -> float:
        """Let ``wall_dt`` seconds of wall time pass; pauses at the end."""
        if self.playing and wall_dt > 0:
            self.seek(self.t + self.speed * wall_dt)
            if self.t >= self.duration:
                self.playing = False
        return self.t
