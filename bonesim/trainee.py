"""The trainee's servo in a process of its own, for the trainee's window.

``bonesim tutor join`` and ``bonesim tutor playback`` drive the trainee's
device at 1 kHz (:class:`bonesim.tutor.Trainee`). With a window, the servo
must never wait for the renderer, so :class:`TraineeProcess` runs it in a
child process and publishes, through shared memory:

``status``
    the latest instructor sample (tool pose, drill, burr, force), the
    trainee's device position and the force written to it, the link gain and
    state, tracking error and latency, ticks and playback time (indices
    ``TS_*``), rewritten after every servo tick;
``changes``
    a ring of the replica's changes in order (see
    :attr:`bonesim.tutor.Source.changes`): the voxels each applied removal
    emptied, and a row of :data:`~bonesim.tutor.RESET_IJK` when the replica
    went back to the initial tissue.

The window (:mod:`bonesim.render.trainee`) keeps its own replica of the
tissue from the ``changes`` ring, as the simulator's window does from the
haptic loop's removal ring. The model (the case the instructor drills, or the
recorded one) and the burr radii reach the parent once, through a pipe, when
the child is ready; its final statistics follow when it ends.
"""
from __future__ import annotations

import math
import time

import numpy as np

from . import events
from .errors import BonesimError
from .shared import SharedArrays, die_with_parent, end_process, start_process, wait_ready

__all__ = ["TS_DONE", "TS_T", "TS_TICKS", "TS_GAIN", "TS_LOST", "TS_VALID", "TS_DRILL",
           "TS_SPEED", "TS_DIR", "TS_BURR", "TS_EPOCH", "TS_ERR_MM", "TS_LATENCY_MS",
           "TS_PLAYBACK_S", "TS_ENDED", "TS_INSTR_POS", "TS_INSTR_AXIS",
           "TS_INSTR_FORCE", "TS_HAND_POS", "TS_FORCE", "N_TS", "C_QUIT",
           "CHANGES_CAPACITY", "changes_ring", "TraineeProcess"]

#: Status vector layout (float64).
(TS_DONE, TS_T, TS_TICKS, TS_GAIN, TS_LOST, TS_VALID, TS_DRILL, TS_SPEED, TS_DIR,
 TS_BURR, TS_EPOCH, TS_ERR_MM, TS_LATENCY_MS, TS_PLAYBACK_S, TS_ENDED) = range(15)
TS_INSTR_POS, TS_INSTR_AXIS, TS_INSTR_FORCE, TS_HAND_POS, TS_FORCE = 15, 18, 21, 24, 27
N_TS = 30
#: Control flags written by the parent.
C_QUIT = 0
#: Capacity of the changes ring (records; 12 MB). A window drains it every
#: frame; falling this far behind would take millions of removals a second.
CHANGES_CAPACITY = 1 << 20


def _spec(capacity: int) -> list:
    return [("status", (N_TS,), np.float64), ("ctl", (1,), np.float64),
            ("changes.ijk", (capacity, 3), np.int32), ("changes.head", (1,), np.int64)]


def changes_ring(arrays: dict) -> events.Ring:
    """The ``changes`` ring over shared arrays."""
    return events.Ring({"ijk": arrays["changes.ijk"]}, arrays["changes.head"])


def _burr_radii(names, default_mm: float) -> list:
    """Burr radius per instructor burr index [mm] (the model's burr where a
    name is not a burr this machine knows)."""
    from .burrs import load_burr

    out = []
    for name in names or ():
        try:
            out.append(float(load_burr(name).radius_mm))
        except (BonesimError, OSError, ValueError):
            out.append(default_mm)
    return out or [default_mm]


def _make_source(spec):
    from . import tutor

    kind = spec[0]
    if kind == "network":
        _, host, port, key, case, timeout_s = spec
        src = tutor.NetworkSource(host, port, key, case=case)
        return src, timeout_s
    if kind == "recording":
        from .session_reader import read_session

        _, path, speed, start_s = spec
        session = read_session(path)
        return tutor.RecordingSource(session, speed=speed, start_s=start_s), None
    raise ValueError(f"unknown trainee source {kind!r} (network or recording)")


def _publisher(status: np.ndarray):
    """``on_tick`` callback writing a :class:`~bonesim.tutor.Trainee`'s
    state into the status vector."""
    t0 = time.monotonic()

    def publish(trainee) -> None:
        src = trainee.source
        st = src.state
        status[TS_T] = time.monotonic() - t0
        status[TS_TICKS] = trainee.ticks
        status[TS_GAIN] = trainee.gain
        status[TS_LOST] = trainee.link_lost
        status[TS_VALID] = st.valid
        status[TS_DRILL] = st.drill
        status[TS_SPEED] = st.speed_rpm
        status[TS_DIR] = st.direction
        status[TS_BURR] = st.burr
        status[TS_EPOCH] = st.epoch
        status[TS_INSTR_POS:TS_INSTR_POS + 3] = st.pos_mm
        status[TS_INSTR_AXIS:TS_INSTR_AXIS + 3] = st.axis
        status[TS_INSTR_FORCE:TS_INSTR_FORCE + 3] = st.force_n
        status[TS_HAND_POS:TS_HAND_POS + 3] = trainee.device_pos
        status[TS_FORCE:TS_FORCE + 3] = trainee.force_n
        d = st.pos_mm - trainee.device_pos
        status[TS_ERR_MM] = math.sqrt(d @ d) if st.valid else math.nan
        lat = getattr(src, "latency", None)
        status[TS_LATENCY_MS] = math.nan if lat is None else lat.last() * 1e3
        status[TS_PLAYBACK_S] = getattr(src, "t", math.nan)
        status[TS_ENDED] = src.ended

    return publish


def _trainee_main(spec, handle, conn, duration_s: float) -> None:
    """Body of the trainee's process."""
    from .devices import SimulatedHandDevice
    from .tutor import Trainee, warmup

    die_with_parent()
    sh = SharedArrays.attach(handle)
    arr = sh.arrays
    status, ctl = arr["status"], arr["ctl"]
    src = trainee = None
    try:
        try:
            warmup()
            src, timeout_s = _make_source(spec)
            src.changes = changes_ring(arr)
            if timeout_s is not None:
                src.connect(timeout_s)
            trainee = Trainee(src, SimulatedHandDevice())
        except BonesimError as exc:
            conn.send({"error": str(exc)})
            if src is not None:
                src.close()
            return
        names = (src.info.get("burrs") if spec[0] == "network"
                 else [b["name"] for b in src.timeline.session.header["burrs"]])
        conn.send({"model": src.model, "burrs": list(names or ()), "lost_text": src.lost_text,
                   "radii": _burr_radii(names, float(src.model.burr.radius_mm)),
                   "what": (f"instructor at {spec[1]}:{spec[2]}" if spec[0] == "network"
                            else f"recording {spec[1]}"),
                   "duration_s": getattr(getattr(src, "timeline", None), "duration",
                                         math.nan)})
        publish = _publisher(status)
        publish(trainee)
        stats = trainee.follow(duration_s, stop=lambda: ctl[C_QUIT] != 0.0,
                               on_tick=publish)
        conn.send({"stats": stats})
    finally:
        if trainee is not None:
            trainee.close()
        status[TS_DONE] = 1.0
        sh.close()


class TraineeProcess:
    """The trainee's servo (source -> controller -> simulated hand) in a
    child process, publishing its state and the replica's changes.

    Parameters
    ----------
    source : tuple
        ``("network", host, port, key, case, timeout_s)`` to follow a live
        instructor (``case`` None: the one the instructor names), or
        ``("recording", path, speed, start_s)`` for haptic playback.
    duration_s : float
        Stop after this long [s] (default: when the source ends).

    Attributes
    ----------
    model : Model
        The case being drilled (after :meth:`start`).
    burrs : list of str
        The instructor's burr names (``TS_BURR`` indexes them).
    radii : list of float
        Burr radius per instructor burr index [mm].
    what : str
        Whom the trainee follows (for the HUD).
    lost_text : str
        What the HUD says while the source is silent.
    duration_of_source_s : float
        Length of a recording [s] (NaN for a live instructor).
    status : (N_TS,) float64
        Shared status vector (``TS_*``).
    changes : events.Ring
        The replica's changes, in order.
    stats : dict
        The servo's final statistics (after the process ended and
        :meth:`stop` or :meth:`close` collected them).
    """

    def __init__(self, source: tuple, duration_s: float = math.inf,
                 capacity: int = CHANGES_CAPACITY):
        self.source = tuple(source)
        self.duration_s = float(duration_s)
        self._sh = SharedArrays.create(_spec(capacity))
        self.status = self._sh.arrays["status"]
        self.ctl = self._sh.arrays["ctl"]
        self.changes = changes_ring(self._sh.arrays)
        self._proc = None
        self._conn = None
        self.model = None
        self.radii = [1.0]
        self.burrs: list = []
        self.lost_text = ""
        self.what = ""
        self.duration_of_source_s = math.nan
        self.stats: dict = {}

    def start(self, timeout_s: float = 60.0) -> "TraineeProcess":
        """Start the child and wait until it follows its source.

        Raises
        ------
        BonesimError
            The source failed (no answer from the instructor, a bad file):
            the child's own message.
        """
        import multiprocessing as mp

        mine, theirs = mp.get_context("spawn").Pipe(duplex=False)
        self._proc = start_process(_trainee_main, "bonesim-trainee",
                                   (self.source, self._sh.handle, theirs, self.duration_s))
        theirs.close()
        self._conn = mine
        wait_s = timeout_s + (self.source[5] if self.source[0] == "network" else 0.0)
        # the child's first message (the model, or its error) says it is
        # ready; it is larger than a pipe's buffer, so read it as it comes
        got = wait_ready(self._proc, self._conn.poll, wait_s)
        msg = {}
        if got == "ready" or self._conn.poll(1.0):
            try:
                msg = self._conn.recv()
            except EOFError:
                pass
        if "model" not in msg:
            code = self._proc.exitcode             # (close() forgets the process)
            self.close()
            raise BonesimError(msg.get("error") or (
                "the trainee process did not start in time" if got == "timeout" else
                f"the trainee process exited during start-up (exit code {code})"))
        self.model = msg["model"]
        self.burrs = list(msg["burrs"])
        self.lost_text = msg["lost_text"]
        self.radii = list(msg["radii"])
        self.what = msg["what"]
        self.duration_of_source_s = float(msg["duration_s"])
        return self

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def done(self) -> bool:
        """The servo has ended (its force ramped out)."""
        return bool(self.status[TS_DONE])

    def radius_mm(self, burr: int) -> float:
        """Radius of the instructor's burr ``burr`` [mm]."""
        return self.radii[burr] if 0 <= burr < len(self.radii) else self.radii[0]

    def _collect(self, timeout_s: float) -> None:
        c = self._conn
        while c is not None and c.poll(timeout_s):
            try:
                msg = c.recv()
            except EOFError:
                break
            if "stats" in msg:
                self.stats = msg["stats"]
                break

    def stop(self, timeout_s: float = 5.0) -> dict:
        """Ask the servo to stop (its force ramps out) and wait; returns the
        final statistics."""
        self.ctl[C_QUIT] = 1.0
        if self._proc is not None:
            self._collect(timeout_s)
            end_process(self._proc, timeout_s)
        return self.stats

    def close(self) -> None:
        """Stop the child (if running) and free the shared memory."""
        if self._proc is not None:
            self.stop()
            self._proc = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._sh is not None:
            self._sh.close()
            self._sh = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
