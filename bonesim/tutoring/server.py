"""The instructor's side of haptic tutoring: the :class:`Streamer` that turns
the haptic loop's samples and tissue events into STATE packets, and the
:class:`TutorServer` process that serves them to trainees."""
from __future__ import annotations

import math
import time

import numpy as np

from bonesim.engine import events
from bonesim.net import packets as net
from bonesim.runtime.child import ChildProcess
from bonesim.net.packets import udp_socket
from bonesim.net.tutor_protocol import (ACK, CLIENT_TIMEOUT_S, DEFAULT_PORT, FLAG_NACK, KIND_STATE,
                                        MAX_BURST, MAX_EVENTS, SERVO_HZ, STALE_S, TissueLog, pack_state,
                                        session_info, tissue_snapshot)

__all__ = ["Streamer", "STATUS_EVERY_TICKS", "TutorServer"]


# -------------------------------------------------------------------- server
class Streamer:
    """The instructor side of tutoring, one :meth:`tick` at a time.

    It reads the haptic loop's ``samples`` and ``tissue`` rings (in shared
    memory when run by :class:`TutorServer`), keeps the current epoch's
    tissue events in a :class:`~bonesim.net.tutor_protocol.TissueLog` (every kind:
    removals, contacts and injuries, resets, burr changes, splits, poses),
    answers JOINs and ACKs, and sends each streaming trainee a STATE packet
    per new sample (more while it is behind the log, see
    :data:`~bonesim.net.tutor_protocol.MAX_BURST`). A ``RESET`` in the stream
    starts a new log; the samples' ``epoch`` column is not read.

    Parameters
    ----------
    sock : socket.socket
        Bound, non-blocking UDP socket (anything with ``sendto`` and
        ``recvfrom_into``).
    key : bytes
    samples, tissue : events.Ring
        The loop's rings; the tissue ring is read from its current count on.
    info : dict
        Session description sent in WELCOME (:func:`session_info`).
    snapshot : dict or callable, optional
        Tissue events that bring the case's initial tissue to the live one
        now, beginning with a ``RESET``
        (:func:`~bonesim.net.tutor_protocol.tissue_snapshot`): the log of a
        server started mid-session. A callable returning them is called
        after the tissue ring's cursor is set, so that what the loop changes
        meanwhile is logged after the snapshot (a replica applies an event
        the snapshot already shows harmlessly). Default: a ``RESET`` of
        epoch 0 alone (a server started with the loop).

    Attributes
    ----------
    log : TissueLog
    epoch : int
        The log's epoch (its leading ``RESET``'s ``n``).
    counters : dict
        ``sent``, ``events_sent``, ``nacks``, ``go_backs`` and the session's
        ``joins``, ``welcomes``, ``send_errors``, ``peers_dropped``
        (:class:`bonesim.net.packets.SessionServer`); :attr:`rx` holds the received
        datagrams by outcome.
    """

    def __init__(self, sock, key: bytes, samples: events.Ring, tissue: events.Ring,
                 info: dict, snapshot=None):
        self.samples = samples
        self.tissue = tissue
        self.log = TissueLog()
        self.counters = dict.fromkeys(("sent", "events_sent", "nacks", "go_backs"), 0)
        self.session = net.SessionServer(sock, key, info, stale_s=STALE_S,
                                         timeout_s=CLIENT_TIMEOUT_S, counters=self.counters,
                                         make_peer=self._new_trainee)
        self._pbuf = bytearray(net.MAX_PAYLOAD)
        self._sf = samples.fields
        self._smask = samples.capacity - 1
        n = samples.count
        self.s_pos = n
        self.t_done = float(self._sf["t_s"][(n - 1) & self._smask]) if n else -math.inf
        self.r_pos = tissue.count              # cursor first, then the snapshot
        if callable(snapshot):
            snapshot = snapshot()
        if snapshot is None:
            snapshot = events.empty_events(1)
            snapshot["kind"][0] = events.RESET
        if len(snapshot["kind"]) == 0 or snapshot["kind"][0] != events.RESET:
            raise ValueError("a tutoring snapshot begins with a RESET event")
        self.epoch = 0
        self._take(snapshot)

    @staticmethod
    def _new_trainee(peer) -> None:
        peer.send_from = 0                     # next log index to send it
        peer.acked = 0                         # events it holds
        peer.last_sent_sample = -1

    @property
    def clients(self) -> dict:
        """Joined trainees by address (:class:`bonesim.net.packets.Peer`)."""
        return self.session.peers

    @property
    def rx(self) -> dict:
        """Received datagrams by outcome (:data:`bonesim.net.packets.COUNTERS`)."""
        return self.session.rx

    # ------------------------------------------------------------- inputs
    def _take(self, ev: dict) -> None:
        """Log tissue events; from the last ``RESET`` among them, a new log."""
        resets = np.flatnonzero(ev["kind"] == events.RESET)
        if len(resets):
            r = int(resets[-1])
            ev = {f: a[r:] for f, a in ev.items()}
            self.log.clear()
            self.epoch = int(ev["n"][0])
            for c in self.clients.values():
                c.send_from = 0
                c.acked = 0
        if len(ev["kind"]):
            self.log.extend(ev)

    def _pump(self) -> None:
        """Take the samples and tissue events published since the last call."""
        n = self.samples.count
        if n == self.s_pos:
            return
        t_last = float(self._sf["t_s"][(n - 1) & self._smask])
        # events of completed steps only (their sample is out): t <= t_last
        r_n = self.tissue.count
        if r_n > self.r_pos:
            rec = self.tissue.read(self.r_pos, r_n)
            done = int(np.searchsorted(rec["t_s"], t_last, side="right"))
            if done:
                self._take({f: a[:done] for f, a in rec.items()})
            self.r_pos += done
        self.s_pos = n
        self.t_done = t_last

    def _ack(self, c, p) -> None:
        if len(p.payload) != ACK.size:
            self.rx["malformed"] += 1
            self.rx["accepted"] -= 1
            return
        have, epoch = ACK.unpack(p.payload)
        if not c.streaming:
            c.streaming = True
            c.send_from = 0
        if epoch != self.epoch or have > self.log.n:
            return                                    # about another epoch: ignore
        c.acked = max(c.acked, have)
        if p.flags & FLAG_NACK:
            self.counters["nacks"] += 1
            if have < c.send_from:
                c.send_from = have
                self.counters["go_backs"] += 1

    # --------------------------------------------------------------- tick
    def tick(self, now: float) -> int:
        """Receive, take new data, send at time ``now`` [s] (the clock the
        packets are stamped with). Returns the STATE packets sent."""
        for c, p in self.session.receive(now):
            self._ack(c, p)
        self._pump()
        head = self.s_pos
        if head == 0:
            return 0
        q = (head - 1) & self._smask
        f = self._sf
        log = self.log
        sent = 0
        for c in self.session.expire(now):
            if not c.streaming:
                continue
            pending = log.n - c.send_from
            if head == c.last_sent_sample and pending <= 0:
                continue
            for _ in range(MAX_BURST):
                k = min(max(pending, 0), MAX_EVENTS)
                a = c.send_from
                n = pack_state(self._pbuf, f["t_s"][q], f["pos_mm"][q], f["axis"][q],
                               f["force_n"][q], f["speed_rpm"][q], f["mag_n"][q],
                               f["volume_mm3"][q], self.epoch, int(f["buttons"][q]),
                               int(f["drill"][q]), int(f["direction"][q]),
                               int(f["burr"][q]), log.n, a, log.rec[a:a + k])
                self.session.send(c, KIND_STATE, memoryview(self._pbuf)[:n])
                c.send_from += k
                pending -= k
                self.counters["sent"] += 1
                self.counters["events_sent"] += k
                sent += 1
                if pending <= 0:
                    break
            c.last_sent_sample = head
        return sent

    def drain(self, clock, period_s: float, timeout_s: float = 0.5) -> bool:
        """Before the BYE: go on ticking until every streaming trainee holds
        every logged tissue event (acknowledged), or ``timeout_s`` [s] has
        passed; ``clock`` is the ticks' clock [s], ``period_s`` their spacing.
        Returns whether all trainees hold all events (the session's last
        removals are not lost by ending it)."""
        end = clock() + float(timeout_s)
        while True:
            self.tick(clock())
            if all(c.acked >= self.log.n for c in self.clients.values() if c.streaming):
                return True
            if clock() >= end:
                return False
            time.sleep(period_s)

    def bye(self) -> None:
        """Tell every trainee the session ends."""
        self.session.bye()

    def stats(self) -> dict:
        return {**self.counters, "received": dict(self.rx), "clients": len(self.clients),
                "streaming": sum(c.streaming for c in self.clients.values()),
                "log_events": self.log.n, "epoch": self.epoch}


# server process ------------------------------------------------------------
#: The server refreshes its shared status every this many ticks.
STATUS_EVERY_TICKS = 64


def _snapshot_of(arrays: dict, samples: events.Ring, initial_density, label,
                 bricks) -> dict:
    """The live tissue in the loop's shared ``arrays`` as snapshot events,
    stamped with the latest sample's time and epoch (the epoch only names
    the snapshot's ``RESET``; later resets come as events)."""
    n = samples.count
    q = (n - 1) & (samples.capacity - 1)
    epoch = int(samples.fields["epoch"][q]) if n else 0
    t_s = float(samples.fields["t_s"][q]) if n else 0.0
    return tissue_snapshot(initial_density, label, bricks, arrays["density"],
                           arrays["body"], arrays["pose"], arrays["alive"], epoch, t_s)


def _run_server(child, loop_handle, host, port, key, rate_hz, info, initial_density,
                label, bricks) -> None:
    """Body of the server process: attach to the loop, stream until told to quit."""
    from bonesim.runtime.haptic_loop import attach

    sh, rings = attach(loop_handle)
    status = child.status
    sock = None
    stats = {}
    try:
        sock = udp_socket(host, port)          # a BonesimError here reaches start()
        streamer = Streamer(sock, key, rings["samples"], rings["tissue"], info,
                            snapshot=lambda: _snapshot_of(sh.arrays, rings["samples"],
                                                          initial_density, label, bricks))
        status["port"] = sock.getsockname()[1]
        child.ready()
        period = 1.0 / rate_hz
        clock = time.monotonic
        deadline = clock()
        ticks = 0
        while not child.quit:
            streamer.tick(clock())
            ticks += 1
            if ticks % STATUS_EVERY_TICKS == 0:
                c = streamer.counters
                status["clients"] = len(streamer.clients)
                status["sent"] = c["sent"]
                status["events_sent"] = c["events_sent"]
                status["nacks"] = c["nacks"]
                status["go_backs"] = c["go_backs"]
                status["log_events"] = streamer.log.n
                status["ticks"] = ticks
            deadline += period
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest)
            elif rest < -10 * period:                 # fell far behind: do not burst
                deadline = clock()
        streamer.drain(clock, period)          # the last events reach every trainee
        streamer.bye()
        stats = streamer.stats()
        stats["ticks"] = ticks
    finally:
        if sock is not None:
            child.send(stats)                  # the final figures, for stop()
            sock.close()
        rings.clear()
        sh.close()


class TutorServer(ChildProcess):
    """Streams a running :class:`~bonesim.runtime.haptic_loop.HapticLoop` to trainees
    from its own process, attached to the loop's shared memory, so that
    neither the loop nor a window in the main process delays sending.

    Parameters
    ----------
    loop : HapticLoop
        Started or about to be (its rings must exist: the shared memory).
    key : bytes
        Shared packet key (:func:`bonesim.net.packets.load_key`).
    host : str
        Address to bind ("0.0.0.0": every interface; "127.0.0.1": local only).
    port : int
        UDP port (0: any free one, see :attr:`port`).
    rate_hz : float
        Send rate [Hz] (the haptic rate).

    Attributes
    ----------
    final : dict
        The server's final statistics (after :meth:`stop`).
    """

    NAME = "bonesim-tutor-server"
    STATUS = (("port", np.int64), ("clients", np.int64), ("sent", np.int64),
              ("events_sent", np.int64), ("nacks", np.int64), ("go_backs", np.int64),
              ("log_events", np.int64), ("ticks", np.int64))
    START_TIMEOUT_S = 30.0

    def __init__(self, loop, key: bytes, host: str = "0.0.0.0", port: int = DEFAULT_PORT,
                 rate_hz: float = SERVO_HZ):
        self.loop = loop
        self.key = bytes(key)
        self.host = host
        self.port = int(port)
        self.rate_hz = float(rate_hz)
        self.final: dict = {}
        super().__init__()

    def child_args(self) -> dict:
        model = self.loop.model
        burrs = [b for b in self.loop.burrs if b is not None]
        return {"loop_handle": self.loop.handle, "host": self.host, "port": self.port,
                "key": self.key, "rate_hz": self.rate_hz,
                "info": session_info(model, burrs),
                "initial_density": np.asarray(model.grid.density),
                "label": np.asarray(model.grid.label),
                "bricks": np.asarray(model.grid.bricks)}

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_server(child, **kwargs)

    def start(self, timeout_s: float | None = None) -> "TutorServer":
        """Start the server; :attr:`port` is the bound one after.

        Raises
        ------
        ProcessFailed
            The address could not be bound (its message says why), or the
            process died or did not start in time.
        """
        super().start(timeout_s)
        self.port = int(self.status["port"])
        return self

    def figures(self) -> dict:
        """Live figures (refreshed every :data:`STATUS_EVERY_TICKS` ticks)."""
        s = self.status
        return {k: int(s[k]) for k in ("clients", "sent", "events_sent", "nacks",
                                        "go_backs", "log_events", "ticks")}

    def stop(self, timeout_s: float = 5.0) -> dict:
        """Say BYE to the trainees, stop the process; returns its final stats."""
        super().stop(timeout_s)
        if self.messages:
            self.final = self.messages[-1]
        return self.final

    def close(self) -> dict:
        """:meth:`stop`, then free the shared memory; returns the final stats."""
        super().close()
        return self.final
