"""Where a trainee's instructor state comes from: a live :class:`NetworkSource`
(an instructor's server over UDP) or a :class:`RecordingSource` (a recorded
session: haptic playback)."""
from __future__ import annotations

import math
import time

import numpy as np

from . import net
from .errors import BonesimError
from .tutor_protocol import (ACK, FLAG_NACK, JOIN_RETRY_S, KEEPALIVE_S, KIND_STATE,
                             NACK_HOLD_S, REJOIN_S, RESET_IJK, STALE_S, InstructorState,
                             unpack_state)

__all__ = ["Source", "NetworkSource", "RecordingSource"]


# ------------------------------------------------------------------- sources
class Source:
    """Where a :class:`Trainee` gets the instructor's state.

    Attributes
    ----------
    state : InstructorState
        The latest instructor sample.
    grid : Grid or None
        The trainee's replica of the instructor's tissue.
    last_valid_s : float
        Trainee clock of the last valid data [s] (NaN before any).
    lost_text : str
        HUD text while the source is silent.
    changes : events.Ring or None
        Set it to a ring with an ``ijk`` (int32 (3,)) column to have every
        change to :attr:`grid` published in order, for a display in another
        process (:mod:`bonesim.trainee`): the voxels each applied removal
        emptied, and a row of :data:`RESET_IJK` whenever the replica went
        back to the initial tissue (a case reset, a new session).
    """

    lost_text = "LINK LOST"
    changes = None

    def poll(self, now_s: float) -> None:
        """Take whatever arrived by ``now_s`` (trainee clock [s])."""
        raise NotImplementedError

    @property
    def ended(self) -> bool:
        """No more data will come (the instructor said BYE, the recording ended)."""
        return False

    def _publish(self, ijk) -> None:
        if self.changes is not None and len(ijk):
            self.changes.append(ijk=ijk)

    def _publish_reset(self) -> None:
        if self.changes is not None:
            self.changes.append(ijk=RESET_IJK)

    def stats(self) -> dict:
        return {}

    def close(self) -> None:
        pass


class _LatencyLog:
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
        The case the instructor drills (its grid is replicated). Default:
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
        Removals of the current epoch applied to :attr:`grid`.
    welcomed : bool
    info : dict
        The instructor's session description (from WELCOME).
    """

    def __init__(self, host: str, port: int, key: bytes, model=None, sock=None,
                 case: str | None = None):
        self.counters = dict.fromkeys(("acks_sent", "nacks_sent", "removals_applied",
                                       "removals_skipped", "resets", "states"), 0)
        self.link = net.SessionClient(host, port, key, (KIND_STATE,), stale_s=STALE_S,
                                      join_retry_s=JOIN_RETRY_S, rejoin_s=REJOIN_S,
                                      sock=sock, what="instructor", counters=self.counters)
        self.model = model
        self.case = case
        self.grid = None if model is None else model.grid.copy()
        self.state = InstructorState()
        self.have = 0
        self.epoch = None
        self._last_ack = -math.inf
        self._nack_have = -1
        self._nack_at = -math.inf
        self._empty = np.zeros((0, 3), np.int32)
        #: ``now - t_s`` of every STATE packet [s]: the one-way latency on one
        #: machine (shared monotonic clock); across machines it also holds the
        #: clocks' offset, and only its spread (``delay_over_fastest_ms``) means much.
        self.latency = _LatencyLog()

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
            if self.model is None:
                self.model = self._load_model(info)
            if int(info.get("n_bricks", -1)) != self.model.grid.n_bricks:
                raise BonesimError(
                    f"the instructor's case {info.get('case')!r} has "
                    f"{info.get('n_bricks')} bricks, this trainee's "
                    f"{self.model.name!r} has {self.model.grid.n_bricks}: not the same case",
                    field="--case")
            self._reset_replica(None)
        self._ack(now, False)

    def _load_model(self, info: dict):
        from pathlib import Path

        from .loading import load_model

        src = self.case or info.get("case")
        if self.case is None and info.get("case_path") and Path(info["case_path"]).exists():
            src = str(Path(info["case_path"]).parent)
        burr = (info.get("burrs") or ["cutting-5mm"])[0]
        try:
            return load_model(src, burr)
        except BonesimError:
            return load_model(src, "cutting-5mm")     # the burr matters only for display

    def _reset_replica(self, epoch) -> None:
        self.grid = self.model.grid.copy()
        self.grid.density.flags.writeable = True
        self.have = 0
        self.epoch = epoch
        self.counters["resets"] += 1
        self._publish_reset()

    def _state(self, p, now: float) -> None:
        from .grid import sync_replica

        log_len, first, ijk = unpack_state(p.payload, self.state)
        self.counters["states"] += 1
        self.link.last_valid_s = now
        self.latency.add(now - p.t_s)
        if self.state.epoch != self.epoch:
            self._reset_replica(self.state.epoch)
        k = len(ijk)
        if first > self.have:                         # a gap: ask to go back
            self.counters["removals_skipped"] += k
            if self.have != self._nack_have or now - self._nack_at > NACK_HOLD_S:
                self._nack_have = self.have
                self._nack_at = now
                self._ack(now, True)
            return
        skip = self.have - first
        if skip < k:
            sync_replica(self.grid, self.grid, ijk[skip:], self._empty)
            self._publish(ijk[skip:])
            self.have = first + k
            self.counters["removals_applied"] += k - skip

    @property
    def ended(self) -> bool:
        """The instructor said BYE."""
        return self.counters["byes"] > 0

    def poll(self, now_s: float) -> None:
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
                "have_removals": self.have, "epoch": self.epoch,
                "latency_ms": _pcts_ms(lat),
                "delay_over_fastest_ms": _pcts_ms(lat - lat.min() if len(lat) else lat)}

    def close(self) -> None:
        self.link.close()


class RecordingSource(Source):
    """A recorded session played back in real time (haptic playback).

    Parameters
    ----------
    session : Session
        From :func:`bonesim.session_reader.read_session`.
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
    """

    lost_text = "PLAYBACK ENDED"

    def __init__(self, session, model=None, speed: float = 1.0, start_s: float = 0.0):
        from .playback import Timeline

        if not speed > 0:
            raise BonesimError(f"playback speed must be positive, got {speed}",
                               field="--speed")
        self.timeline = Timeline(session)
        self.model = model if model is not None else session.load_model(check=False)
        self.speed = float(speed)
        self.start_s = self.timeline.clamp(start_s)
        self.state = InstructorState()
        self.grid = self.model.grid.copy()
        self.epoch = None
        self.applied = 0
        self.t = self.start_s
        self.done = False
        self.last_valid_s = math.nan
        self._t0 = math.nan
        self._empty = np.zeros((0, 3), np.int32)

    def poll(self, now_s: float) -> None:
        from .grid import sync_replica

        if self._t0 != self._t0:
            self._t0 = now_s
        tl = self.timeline
        if self.done:
            return                                    # no new data: the force ramps out
        t = self.start_s + (now_s - self._t0) * self.speed
        if t >= tl.duration:
            # this poll shows the end of the recording (the removals since the
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
        st.epoch = int(s["epoch"][i])
        st.valid = True
        self.last_valid_s = now_s
        epoch, lo, hi = tl.removal_range(t)
        if epoch != self.epoch:
            self.grid = self.model.grid.copy()
            self.epoch = epoch
            self.applied = lo
            self._publish_reset()
        if hi > self.applied:
            sync_replica(self.grid, self.grid, tl.rem_ijk[self.applied:hi], self._empty)
            self._publish(tl.rem_ijk[self.applied:hi])
            self.applied = hi

    @property
    def ended(self) -> bool:
        return self.done

    def stats(self) -> dict:
        return {"playback_s": round(self.t, 4), "duration_s": round(self.timeline.duration, 4),
                "done": self.done, "speed": self.speed}
