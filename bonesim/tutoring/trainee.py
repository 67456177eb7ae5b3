"""The trainee's servo in a process of its own, for the trainee's window.

``bonesim tutor join`` and ``bonesim tutor playback`` drive the trainee's
device at 1 kHz (:class:`bonesim.tutoring.servo.Trainee`). With a window, the servo
must never wait for the renderer, so :class:`TraineeProcess` runs it in a
child process and publishes, through shared memory:

``status``
    the latest instructor sample (tool pose, drill, burr, force), the
    trainee's device position and the force written to it, the link gain and
    state, tracking error and latency, ticks and playback time (named fields,
    :data:`STATUS`: ``proc.status["ticks"]``), rewritten after every servo
    tick; ``done`` once the servo has ended;
``changes``
    a ring of tissue-event records (:data:`bonesim.engine.events.TISSUE_FIELDS`,
    the ring spec ``changes`` of :data:`bonesim.engine.events.OTHER_RINGS`): every
    event the source applied to its replica, in order (see
    :attr:`bonesim.tutoring.sources.Source.changes`), beginning with a ``RESET``.

The window (:mod:`bonesim.render.trainee`) applies the ``changes`` ring to
its own :class:`~bonesim.engine.replica.TissueReplica` (with a surface), as the
simulator's window applies the haptic loop's tissue ring; its reset handling
comes from the ``RESET`` events. The model (the case the instructor drills, or the
recorded one) and the burr radii reach the parent once, through a pipe, when
the child is ready; its final statistics follow when it ends.
"""
from __future__ import annotations

import math
import time

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError, ProcessFailed
from bonesim.runtime.child import ChildProcess

__all__ = ["STATUS", "CHANGES_CAPACITY", "changes_ring", "TraineeProcess"]

#: The servo's status fields (after the process base's).
STATUS = (
    ("t_s", np.float64),                    # since the servo started [s]
    ("ticks", np.int64),
    ("gain", np.float64),                   # link gain (0..1)
    ("lost", np.uint8),                     # the source is silent
    ("valid", np.uint8),                    # an instructor sample was received
    ("drill", np.uint8),
    ("speed_rpm", np.float64),
    ("direction", np.int8),
    ("burr", np.int32),                     # the instructor's burr index
    ("epoch", np.int64),
    ("err_mm", np.float64),                 # tracking error (NaN: none) [mm]
    ("latency_ms", np.float64),             # last packet's latency (NaN: none) [ms]
    ("playback_s", np.float64),             # position in a recording [s]
    ("ended", np.uint8),                    # the source ended
    ("instr_pos_mm", np.float64, (3,)),     # the instructor's tool [mm]
    ("instr_axis", np.float64, (3,)),
    ("instr_force_n", np.float64, (3,)),    # the instructor's force [N]
    ("hand_mm", np.float64, (3,)),          # the trainee's device [mm]
    ("force_n", np.float64, (3,)),          # written to the trainee's device [N]
)
#: Capacity of the changes ring (tissue events; 83 bytes each, 43 MB). A
#: window drains it every frame; falling this far behind would take millions
#: of events a second (or a playback started late in a session of more
#: events since its last reset).
CHANGES_CAPACITY = events.OTHER_RINGS["changes"][0]


def changes_ring(arrays: dict) -> events.Ring:
    """The ``changes`` ring (tissue events) over shared arrays."""
    return events.ring_from_arrays("changes", arrays)


def _burr_radii(names, default_mm: float) -> list:
    """Burr radius per instructor burr index [mm] (the model's burr where a
    name is not a burr this machine knows)."""
    from bonesim.io.burrs import load_burr

    out = []
    for name in names or ():
        try:
            out.append(float(load_burr(name).radius_mm))
        except (BonesimError, OSError, ValueError):
            out.append(default_mm)
    return out or [default_mm]


def _make_source(spec):
    from bonesim.tutoring.sources import NetworkSource, RecordingSource

    kind = spec[0]
    if kind == "network":
        _, host, port, key, case, timeout_s = spec
        src = NetworkSource(host, port, key, case=case)
        return src, timeout_s
    if kind == "recording":
        from bonesim.session.reader import read_session

        _, path, speed, start_s = spec
        session = read_session(path)
        return RecordingSource(session, speed=speed, start_s=start_s), None
    raise ValueError(f"unknown trainee source {kind!r} (network or recording)")


def _publisher(status: np.ndarray):
    """``on_tick`` callback writing a :class:`~bonesim.tutoring.servo.Trainee`'s
    state into the status record."""
    t0 = time.monotonic()

    def publish(trainee) -> None:
        src = trainee.source
        st = src.state
        status["t_s"] = time.monotonic() - t0
        status["ticks"] = trainee.ticks
        status["gain"] = trainee.gain
        status["lost"] = trainee.link_lost
        status["valid"] = st.valid
        status["drill"] = st.drill
        status["speed_rpm"] = st.speed_rpm
        status["direction"] = st.direction
        status["burr"] = st.burr
        status["epoch"] = st.epoch
        status["instr_pos_mm"] = st.pos_mm
        status["instr_axis"] = st.axis
        status["instr_force_n"] = st.force_n
        status["hand_mm"] = trainee.device_pos
        status["force_n"] = trainee.force_n
        d = st.pos_mm - trainee.device_pos
        status["err_mm"] = math.sqrt(d @ d) if st.valid else math.nan
        lat = getattr(src, "latency", None)
        status["latency_ms"] = math.nan if lat is None else lat.last() * 1e3
        status["playback_s"] = getattr(src, "t", math.nan)
        status["ended"] = src.ended

    return publish


def _run_trainee(child, spec, duration_s: float, device: str | None = None) -> None:
    """Body of the trainee's process (:meth:`TraineeProcess.run`)."""
    from bonesim.tutoring.servo import Trainee, warmup

    src = trainee = None
    try:
        try:
            warmup()
            src, timeout_s = _make_source(spec)
            src.changes = changes_ring(child.arrays)
            if timeout_s is not None:
                src.connect(timeout_s)
            if spec[0] == "recording":
                tl = src.timeline
                start = tl.samples["pos_mm"][tl.sample_index(src.start_s)]
            else:
                start = src.state.pos_mm
            dev, record = open_trainee_device(device, src, start)
            try:
                trainee = Trainee(src, dev)
            except BaseException:
                dev.close()
                raise
        except BaseException:
            if src is not None:
                src.close()
            raise
        names = (src.info.get("burrs") if spec[0] == "network"
                 else [b["name"] for b in src.timeline.session.header["burrs"]])
        publish = _publisher(child.status)
        publish(trainee)
        child.ready()
        # larger than a pipe's buffer: sent after ready, read by start()
        child.send({"model": src.model, "burrs": list(names or ()),
                    "lost_text": src.lost_text,
                    "radii": _burr_radii(names, float(src.model.burr.radius_mm)),
                    "what": (f"instructor at {spec[1]}:{spec[2]}" if spec[0] == "network"
                             else f"recording {spec[1]}"),
                    "duration_s": getattr(getattr(src, "timeline", None), "duration",
                                          math.nan)})
        stats = trainee.follow(duration_s, stop=lambda: child.quit, on_tick=publish)
        stats["device_record"] = record
        child.send({"stats": stats})
    finally:
        if trainee is not None:
            trainee.close()
            trainee.device.close()


def open_trainee_device(name, src, start_mm) -> tuple:
    """``(device, record)``: the bare simulated hand when ``name`` is None,
    else the backend behind the safety layer
    (:func:`bonesim.tutoring.devices.trainee_device`)."""
    if name is None:
        from bonesim.devices.registry import device_record
        from bonesim.devices.simulated_hand import SimulatedHandDevice

        hand = SimulatedHandDevice()
        return hand, device_record("simulated-hand", hand)
    from bonesim.tutoring.devices import trainee_device

    return trainee_device(name, np.array(start_mm, float), src.model.case)


class TraineeProcess(ChildProcess):
    """The trainee's servo (source -> controller -> simulated hand) in a
    child process, publishing its state and the tissue events it applied.

    Parameters
    ----------
    source : tuple
        ``("network", host, port, key, case, timeout_s)`` to follow a live
        instructor (``case`` None: the one the instructor names), or
        ``("recording", path, speed, start_s)`` for haptic playback.
    duration_s : float
        Stop after this long [s] (default: when the source ends).
    device : str, optional
        The trainee's device backend (default: the bare simulated hand).
    capacity : int
        Tissue events the changes ring holds (a power of two).

    Attributes
    ----------
    model : Model
        The case being drilled (after :meth:`start`).
    burrs : list of str
        The instructor's burr names (``status["burr"]`` indexes them).
    radii : list of float
        Burr radius per instructor burr index [mm].
    what : str
        Whom the trainee follows (for the HUD).
    lost_text : str
        What the HUD says while the source is silent.
    duration_of_source_s : float
        Length of a recording [s] (NaN for a live instructor).
    status : ndarray
        Shared status record (:data:`STATUS`).
    changes : events.Ring
        The tissue events the servo's source applied, in order.
    stats : dict
        The servo's final statistics (after the process ended and
        :meth:`stop` or :meth:`close` collected them).
    """

    NAME = "bonesim-trainee"

    STATUS = STATUS

    def __init__(self, source: tuple, duration_s: float = math.inf,
                 capacity: int = CHANGES_CAPACITY, device: str | None = None):
        self.source = tuple(source)
        self.device = device
        self.duration_s = float(duration_s)
        self.capacity = int(capacity)
        super().__init__()
        self.changes = changes_ring(self.arrays)
        self.model = None
        self.radii = [1.0]
        self.burrs: list = []
        self.lost_text = ""
        self.what = ""
        self.duration_of_source_s = math.nan
        self.stats: dict = {}

    def shared_spec(self) -> list:
        return events.ring_arrays_spec("changes", self.capacity)

    def child_args(self) -> dict:
        return {"spec": self.source, "duration_s": self.duration_s, "device": self.device}

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_trainee(child, **kwargs)

    def start(self, timeout_s: float | None = None) -> "TraineeProcess":
        """Start the child and wait until it follows its source.

        Raises
        ------
        ProcessFailed
            The source failed (no answer from the instructor, a bad file):
            the child's own message; or the child died or did not start.
        """
        timeout_s = self.START_TIMEOUT_S if timeout_s is None else timeout_s
        wait_s = timeout_s + (self.source[5] if self.source[0] == "network" else 0.0)
        super().start(wait_s)
        msg = self.receive(wait_s) or {}
        if "model" not in msg:
            self.close()
            raise ProcessFailed(self.NAME, "sent no model after it was ready")
        self.model = msg["model"]
        self.burrs = list(msg["burrs"])
        self.lost_text = msg["lost_text"]
        self.radii = list(msg["radii"])
        self.what = msg["what"]
        self.duration_of_source_s = float(msg["duration_s"])
        return self

    @property
    def done(self) -> bool:
        """The servo has ended (its force ramped out)."""
        return bool(self.status["done"])

    def radius_mm(self, burr: int) -> float:
        """Radius of the instructor's burr ``burr`` [mm]."""
        return self.radii[burr] if 0 <= burr < len(self.radii) else self.radii[0]

    def stop(self, timeout_s: float = 5.0) -> dict:
        """Ask the servo to stop (its force ramps out) and wait; returns the
        final statistics."""
        super().stop(timeout_s)
        for msg in self.messages:
            if "stats" in msg:
                self.stats = msg["stats"]
        return self.stats
