"""Where a trainee's instructor state comes from: a live :class:`NetworkSource`
(an instructor's server over UDP) or a :class:`RecordingSource` (a recorded
session: haptic playback).

Either keeps the trainee's copy of the instructor's tissue in one
:class:`~bonesim.engine.replica.TissueReplica`, changed only by the tissue-event
stream (:mod:`bonesim.engine.events`): the server's log, or the session file's
``tissue`` table. Resets, splits and poses arrive as events like the
removals; the replica's reset handling is the only one.
"""
from __future__ import annotations

import math
import time

import numpy as np

from bonesim.engine import events
from bonesim.net import packets as net
from bonesim.errors import BonesimError
from bonesim.engine.replica import TissueReplica
from bonesim.net.tutor_protocol import (ACK, FLAG_NACK, JOIN_RETRY_S, KEEPALIVE_S, KIND_STATE,
                                        NACK_HOLD_S, REJOIN_S, STALE_S, InstructorState,
                                        check_tissue_version, unpack_state)

__all__ = ["Source", "NetworkSource", "RecordingSource"]


# ------------------------------------------------------------------- sources
class Source:
    """Where a :class:`Trainee` gets the instructor's state.

    Attributes
    ----------
    state : InstructorState
        The latest instructor sample.
    replica : TissueReplica or None
        The trainee's copy of the instructor's tissue (None until the case
        is known).
    last_valid_s : float
        Trainee clock of the last valid data [s] (NaN before any).
    lost_text : str
        HUD text while the source is silent.
    changes : events.Ring or None
        Set it to a tissue-event ring (:data:`bonesim.engine.events.TISSUE_FIELDS`)
        to have every event applied to :attr:`replica` published in order,
        for a display in another process (:mod:`bonesim.tutoring.trainee`) that keeps
        its own replica. The events start with a ``RESET`` (the tissue the
        source starts from).
    """

    lost_text = "LINK LOST"
    changes = None
    replica = None

    @property
    def grid(self):
        """The replica's grid (None until the case is known)."""
        return None if self.replica is None else self.replica.grid

    def poll(self, now_s: float) -> None:
        """Take whatever arrived by ``now_s`` (trainee clock [s])."""
        raise NotImplementedError

    @property
    def ended(self) -> bool:
        """No more data will come (the instructor said BYE, the recording ended)."""
        return False

    def _apply(self, ev: dict) -> None:
        """Apply tissue events (columns) to the replica and publish them."""
        if len(ev["kind"]) == 0:
            return
        self.replica.apply(ev)
        if self.changes is not None:
            self.changes.append(**{f: ev[f] for f in events.TISSUE_FIELDS})

    def stats(self) -> dict:
        return {}

    def close(self) -> None:
        pass


class LatencyLog:
    """Preallocated ring of delays [s] (p50/p99 over the last ``n``)."""

    def __init__(self, n: int = 1 << 16):
        self.v = np.zeros(n)
        self.count = 0

    def add(self, x: float) -> None:
        self.v[self.count & (len(self.v) - 1)] = x
        self.count += 1

    def values(self) -> np.ndarray:
        return self.v[:min(self.count, len(self.v))]

    def last(self) -> float:
        """The latest value (NaN before any)."""
        return float(self.v[(self.count - 1) & (len(self.v) - 1)]) if self.count else math.nan


def _pcts_ms(v) -> dict:
    if len(v) == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": round(float(np.percentile(v, 50)) * 1e3, 4),
            "p99": round(float(np.percentile(v, 99)) * 1e3, 4),
            "max": round(float(v.max()) * 1e3, 4), "n": int(len(v))}


class NetworkSource(Source):
    """An instructor's :class:`TutorServer` over UDP.

    Parameters
    ----------
    host : str
        Instructor's address.
    port : int
    key : bytes
    model : Model, optional
        The case the instructor drills (its tissue is replicated). Default:
        loaded from the WELCOME's description (``case`` override by name or
        manifest path).
    sock : socket, optional
        Bound non-blocking UDP socket (default: any local port); tests pass
        a lossy one.
    case : str, optional
        Case to load instead of the one the instructor names.

    Attributes
    ----------
    have : int
        Events of the server's current log applied to :attr:`replica`.
    epoch : int or None
        The epoch of the log followed (None before the first STATE).
    welcomed : bool
    info : dict
        The instructor's session description (from WELCOME).
    """

    def __init__(self, host: str, port: int, key: bytes, model=None, sock=None,
                 case: str | None = None):
        self.counters = dict.fromkeys(("acks_sent", "nacks_sent", "events_applied",
                                       "events_skipped", "resets", "states"), 0)
        self.link = net.SessionClient(host, port, key, (KIND_STATE,), stale_s=STALE_S,
                                      join_retry_s=JOIN_RETRY_S, rejoin_s=REJOIN_S,
                                      sock=sock, what="instructor", counters=self.counters)
        self.model = model
        self.case = case
        self.replica = None if model is None else TissueReplica(model)
        self.state = InstructorState()
        self.have = 0
        self.epoch = None
        self._last_ack = -math.inf
        self._nack_have = -1
        self._nack_at = -math.inf
        #: ``now - t_s`` of every STATE packet [s]: the one-way latency on one
        #: machine (shared monotonic clock); across machines it also holds the
        #: clocks' offset, and only its spread (``delay_over_fastest_ms``) means much.
        self.latency = LatencyLog()

    # session state, kept by the link
    @property
    def welcomed(self) -> bool:
        return self.link.welcomed

    @property
    def info(self) -> dict:
        return self.link.info

    @property
    def nonce(self) -> int:
        return self.link.nonce

    @property
    def inbox(self) -> net.Inbox:
        return self.link.inbox

    @property
    def last_valid_s(self) -> float:
        """Time of the last WELCOME or STATE accepted [s]."""
        return self.link.last_valid_s

    # --------------------------------------------------------------- send
    def _ack(self, now: float, nack: bool) -> None:
        ep = -1 if self.epoch is None else self.epoch
        self.link.send(net.KIND_ACK, ACK.pack(self.have, ep), FLAG_NACK if nack else 0)
        self._last_ack = now
        self.counters["nacks_sent" if nack else "acks_sent"] += 1

    # ------------------------------------------------------------ receive
    def _welcome(self, new: bool, now: float) -> None:
        if new:                                       # a new server session
            info = self.info
            try:
                check_tissue_version(info.get("tissue_version"), "WELCOME")
            except net.PacketError as exc:
                raise BonesimError(str(exc), field="HOST") from None
            if self.model is None:
                self.model = self._load_model(info)
            if int(info.get("n_bricks", -1)) != self.model.grid.n_bricks:
                raise BonesimError(
                    f"the instructor's case {info.get('case')!r} has "
                    f"{info.get('n_bricks')} bricks, this trainee's "
                    f"{self.model.name!r} has {self.model.grid.n_bricks}: not the same case",
                    field="--case")
            if self.replica is None:
                self.replica = TissueReplica(self.model)
            self.have = 0                  # the new log's leading RESET resets the replica
            self.epoch = None
        self._ack(now, False)

    def _load_model(self, info: dict):
        from bonesim.io.loading import load_model

        src = self.case or info.get("case")
        burr = (info.get("burrs") or ["cutting-5mm"])[0]
        try:
            return load_model(src, burr)
        except BonesimError:
            return load_model(src, "cutting-5mm")     # the burr matters only for display

    def _state(self, p, now: float) -> None:
        try:
            log_len, first, rec = unpack_state(p.payload, self.state)
        except net.PacketError as exc:
            if exc.reason == "version":           # a stream this trainee cannot read
                raise BonesimError(str(exc), field="HOST") from None
            raise
        self.counters["states"] += 1
        self.link.last_valid_s = now
        self.latency.add(now - p.t_s)
        if self.state.epoch != self.epoch:            # a new log (a reset): count from 0
            self.epoch = self.state.epoch
            self.have = 0
        k = len(rec)
        if first > self.have:                         # a gap: ask to go back
            self.counters["events_skipped"] += k
            if self.have != self._nack_have or now - self._nack_at > NACK_HOLD_S:
                self._nack_have = self.have
                self._nack_at = now
                self._ack(now, True)
            return
        skip = self.have - first
        if skip < k:
            new = rec[skip:]
            ev = {f: new[f] for f in events.TISSUE_FIELDS}
            try:
                self._apply(ev)
            except ValueError as exc:
                raise BonesimError(f"the instructor's STATE packet carries a tissue event "
                                   f"this trainee cannot apply: {exc}", field="HOST") from None
            self.have = first + k
            self.counters["events_applied"] += k - skip
            self.counters["resets"] += int(np.count_nonzero(ev["kind"] == events.RESET))

    @property
    def ended(self) -> bool:
        """The instructor said BYE."""
        return self.counters["byes"] > 0

    def poll(self, now_s: float) -> None:
        """Take whatever arrived by ``now_s`` (trainee clock [s]); join and
        acknowledge as the protocol says.

        Raises
        ------
        BonesimError
            The instructor streams tissue-event records of a version this
            trainee does not read (the message names the WELCOME or STATE
            packet), or an event the replica cannot apply.
        """
        for item in self.link.receive(now_s):
            try:
                if isinstance(item, net.Welcome):
                    self._welcome(item.new, now_s)
                elif self.welcomed:
                    self._state(item, now_s)
            except net.PacketError:
                self.link.reject()
        if self.welcomed and now_s - self._last_ack >= KEEPALIVE_S:
            self._ack(now_s, False)

    def connect(self, timeout_s: float = 10.0, clock=time.monotonic) -> None:
        """Join and wait for the WELCOME (and the first instructor sample).

        Raises
        ------
        BonesimError
            If the instructor does not answer in time (wrong address, port or
            key, or a firewall).
        """
        end = clock() + timeout_s
        while not self.state.valid:
            now = clock()
            if now > end:
                bad = self.inbox.counters["auth"]
                why = (f"{bad} packets failed authentication: the key files differ"
                       if bad else "check the address, the port, the key file (the "
                                   "instructor ignores joins under another key) and the "
                                   "firewall")
                addr = self.link.addr
                raise BonesimError(f"no answer from the instructor at {addr[0]}:"
                                   f"{addr[1]} within {timeout_s:g} s ({why})",
                                   field="HOST")
            self.poll(now)
            time.sleep(0.002)

    def stats(self) -> dict:
        lat = self.latency.values()
        return {"packets": dict(self.inbox.counters), **self.counters,
                "have_events": self.have, "epoch": self.epoch,
                "latency_ms": _pcts_ms(lat),
                "delay_over_fastest_ms": _pcts_ms(lat - lat.min() if len(lat) else lat)}

    def close(self) -> None:
        self.link.close()


class RecordingSource(Source):
    """A recorded session played back in real time (haptic playback).

    The instructor's samples come from the session's ``samples`` (through a
    :class:`~bonesim.session.playback.Timeline`), the tissue from its ``tissue``
    event stream (schema 2; schema-1 files are migrated on read): every
    event made at or before the playback time is applied to the replica in
    order, resets included. The replica starts with a ``RESET`` of epoch 0
    (the recording begins with the case's initial tissue); when playback
    starts late, the events before the last reset up to the start are
    skipped.

    Parameters
    ----------
    session : Session
        From :func:`bonesim.session.reader.read_session`.
    model : Model, optional
        The recorded case (default: rebuilt from the session's header).
    speed : float
        Playback speed (1 = as recorded).
    start_s : float
        Playback time to start at [s].

    Attributes
    ----------
    t : float
        Current playback time [s].
    done : bool
        The recording has ended (the trainee's force then ramps to zero).
    stream : dict of str -> ndarray
        The session's tissue events (:data:`bonesim.engine.events.TISSUE_FIELDS`) in
        time order.
    applied : int
        Events of :attr:`stream` handled (applied, or skipped at the start).
    """

    lost_text = "PLAYBACK ENDED"

    def __init__(self, session, model=None, speed: float = 1.0, start_s: float = 0.0):
        from bonesim.session.playback import Timeline

        if not speed > 0:
            raise BonesimError(f"playback speed must be positive, got {speed}",
                               field="--speed")
        self.timeline = Timeline(session)
        self.model = model if model is not None else session.load_model(check=False)
        self.speed = float(speed)
        self.start_s = self.timeline.clamp(start_s)
        self.state = InstructorState()
        self.replica = TissueReplica(self.model)
        tissue = session.tissue
        ev = {f: np.asarray(tissue[f]) for f in events.TISSUE_FIELDS}
        if (np.diff(ev["t_s"]) < 0).any():
            order = np.argsort(ev["t_s"], kind="stable")
            ev = {f: a[order] for f, a in ev.items()}
        self.stream = ev
        self.applied = 0
        self.t = self.start_s
        self.done = False
        self.last_valid_s = math.nan
        self._t0 = math.nan

    def _start(self, hi: int) -> None:
        """The first poll: a RESET, or the stream from its last reset before ``hi``."""
        resets = np.flatnonzero(self.stream["kind"][:hi] == events.RESET)
        if len(resets):
            self.applied = int(resets[-1])
        else:
            start = events.empty_events(1)
            start["kind"][0] = events.RESET
            start["t_s"][0] = self.timeline.t0
            self._apply(start)

    def poll(self, now_s: float) -> None:
        first = self._t0 != self._t0
        if first:
            self._t0 = now_s
        tl = self.timeline
        if self.done:
            return                                    # no new data: the force ramps out
        t = self.start_s + (now_s - self._t0) * self.speed
        if t >= tl.duration:
            # this poll shows the end of the recording (the events since the
            # last poll included); silence after it
            t = tl.duration
            self.done = True
        self.t = t
        i = tl.sample_index(t)
        s, st = tl.samples, self.state
        st.t_s = float(s["t_s"][i])
        st.pos_mm[:] = s["pos_mm"][i]
        st.axis[:] = s["axis"][i]
        st.force_n[:] = s["force_n"][i]
        st.speed_rpm = float(s["speed_rpm"][i])
        st.drill = int(s["drill"][i])
        st.direction = int(s["direction"][i])
        st.burr = int(s["burr"][i])
        st.valid = True
        self.last_valid_s = now_s
        hi = int(np.searchsorted(self.stream["t_s"], tl.t0 + t, side="right"))
        if first:
            self._start(hi)
        if hi > self.applied:
            self._apply({f: a[self.applied:hi] for f, a in self.stream.items()})
            self.applied = hi
        st.epoch = self.replica.epoch

    @property
    def ended(self) -> bool:
        return self.done

    def stats(self) -> dict:
        return {"playback_s": round(self.t, 4), "duration_s": round(self.timeline.duration, 4),
                "done": self.done, "speed": self.speed, "events_applied": self.applied}
