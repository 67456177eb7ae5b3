"""The nerve monitor over the network: a server beside the simulator and the
remote console of the monitoring technician (``bonesim monitor HOST``).

The server (:class:`MonitorServer`) runs inside the monitor process
(:class:`bonesim.runtime.monitor.MonitorProcess` with ``serve=``); the console
(:class:`MonitorConsole`) runs anywhere that reaches it over UDP. Packets are
those of :mod:`bonesim.net.packets` (authenticated with the shared key, nonce,
sequence number, send time), so a console needs the key file, and forged,
replayed, stale or malformed datagrams are dropped and counted.

Wire protocol
-------------
1. The console draws a nonce and sends ``JOIN`` every :data:`JOIN_RETRY_S`
   until welcomed.
2. The server answers ``WELCOME``: its nonce for this console (u64) and a
   JSON description (nerve names and colours, the activity parameters, the
   update and stream rates).
3. Streaming starts with the console's first ``ACK`` (server's nonce); the
   console ACKs every :data:`KEEPALIVE_S` and the server forgets a console
   silent for :data:`CLIENT_TIMEOUT_S`.
4. Every ``1 / stream_hz`` the server sends each console one ``DATA`` packet
   (:data:`KIND_DATA`): the monitor's time and update count, the packet's
   number for that console (so the console counts lost packets), the current
   rate and distance of every nerve, then the spikes since the previous
   packet (time and nerve; more packets follow at once when they do not fit).
   Spikes of lost packets are lost: the console counts them through the gap
   in the numbers, the trace keeps going.
5. Either side may send ``BYE``.

The console keeps a history in the same form as
:meth:`bonesim.runtime.monitor.MonitorView.history`, says when the link is lost
(no data for :data:`LINK_LOSS_S`), measures the packet latency, and can
sound a click per spike (:mod:`bonesim.sound.clicks`).
"""
from __future__ import annotations

import math
import struct
import time
from dataclasses import asdict

import numpy as np

from bonesim.engine import events
from bonesim.net import packets as net
from bonesim.errors import BonesimError
from bonesim.io.anatomy import clinical_name

__all__ = ["DEFAULT_PORT", "STREAM_HZ", "MonitorServer", "MonitorConsole",
           "pack_data", "unpack_data", "run_console"]

#: Default UDP port of the monitor server (the tutoring port + 1).
DEFAULT_PORT = net.MONITOR_PORT
#: Packets per second to each console [Hz].
STREAM_HZ = 50.0
#: Largest extra delay a console accepts [s]. Generous: a late reading is
#: still worth showing (the sequence number, not age, stops replays), and a
#: console sharing a busy machine may read its socket late.
STALE_S = 1.0
#: Console: JOIN retry period [s].
JOIN_RETRY_S = 0.25
#: Console: ACK (keep-alive) period [s].
KEEPALIVE_S = 0.25
#: Console: re-join after this long without data [s].
REJOIN_S = 1.0
#: Console: the link counts as lost after this long without data [s].
LINK_LOSS_S = 0.25
#: Server: forget a console silent this long [s].
CLIENT_TIMEOUT_S = 2.0
#: Server: spikes kept for sending (power of two); a console further behind skips.
SPIKE_LOG = 1 << 14
#: Console: history kept [updates and spikes] (power of two).
HISTORY_CAP = 1 << 14

#: Data packet kind (service kinds start at 16; the monitor has its own port).
KIND_DATA = 32
#: t_s [s], updates, packet number for this console, nerves k, spikes n.
DATA = struct.Struct("<dIIHH")
#: Bytes per nerve (rate, distance as float32) and per spike (time f64, nerve u8).
NERVE_BYTES, SPIKE_BYTES = 8, 9


def _spike_ring(capacity: int) -> events.Ring:
    return events.Ring.create(capacity, t_s=(np.float64, ()), nerve=(np.uint8, ()))


def _history_ring(capacity: int, k: int) -> events.Ring:
    return events.Ring.create(capacity, t_s=(np.float64, ()), rate=(np.float32, (k,)),
                              dist=(np.float32, (k,)))


def max_spikes(k: int) -> int:
    """Spikes one DATA packet carries with ``k`` nerves."""
    return (net.MAX_PAYLOAD - DATA.size - NERVE_BYTES * k) // SPIKE_BYTES


def pack_data(buf, t_s, updates, number, rates, dist, spike_t, spike_n) -> int:
    """Write a DATA payload into ``buf``; returns its length [bytes].

    Parameters
    ----------
    buf : bytearray
        At least :data:`bonesim.net.packets.MAX_PAYLOAD` bytes.
    t_s : float
        Monitor (loop) time of the latest update [s].
    updates : int
        Monitor updates so far.
    number : int
        This packet's number for its console (counts up by one).
    rates, dist : (k,) float
        Rate [spikes/s] and burr-surface distance [mm] of every nerve.
    spike_t : (n,) float64
        Spike times [s]; at most :func:`max_spikes` ``(k)``.
    spike_n : (n,) uint8
        Nerve of each spike.
    """
    k, n = len(rates), len(spike_t)
    if n > max_spikes(k):
        raise ValueError(f"{n} spikes do not fit one packet (at most {max_spikes(k)})")
    DATA.pack_into(buf, 0, t_s, updates & 0xFFFFFFFF, number & 0xFFFFFFFF, k, n)
    o = DATA.size
    for arr, dt in ((rates, "<f4"), (dist, "<f4"), (spike_t, "<f8"), (spike_n, "u1")):
        b = np.asarray(arr, dtype=dt).tobytes()
        buf[o:o + len(b)] = b
        o += len(b)
    return o


def unpack_data(payload) -> dict:
    """Read a DATA payload (see :func:`pack_data`).

    Raises
    ------
    bonesim.net.packets.PacketError
        ``length`` when the sizes in the header disagree with the payload.
    """
    if len(payload) < DATA.size:
        raise net.PacketError("length", f"DATA payload of {len(payload)} bytes is shorter "
                                        f"than its {DATA.size}-byte header")
    t_s, updates, number, k, n = DATA.unpack_from(payload, 0)
    want = DATA.size + NERVE_BYTES * k + SPIKE_BYTES * n
    if len(payload) != want:
        raise net.PacketError("length", f"DATA payload holds {len(payload)} bytes; its "
                                        f"header ({k} nerves, {n} spikes) says {want}")
    o = DATA.size
    out = {"t_s": t_s, "updates": updates, "number": number}
    for key, cnt, dt in (("rate", k, "<f4"), ("dist", k, "<f4"), ("spike_t", n, "<f8"),
                         ("spike_nerve", n, "u1")):
        size = cnt * np.dtype(dt).itemsize
        out[key] = np.frombuffer(payload, dtype=dt, count=cnt, offset=o)
        o += size
    return out


# -------------------------------------------------------------------- server
class MonitorServer:
    """Streams a nerve monitor's rates, distances and spikes to remote consoles.

    Call :meth:`add` after every monitor update and :meth:`poll` often (the
    monitor process does both at its update rate); :meth:`poll` answers
    consoles and sends at ``stream_hz``.

    Parameters
    ----------
    names : list of str
        Monitored nerves (structure names; the consoles show their clinical
        names, sent beside them as ``titles``).
    colors : (k, 3) uint8
        Their display colours.
    params : ActivityParams
        Sent to consoles (scales and warning distance).
    key : bytes
        Shared packet key (:func:`bonesim.net.packets.load_key`).
    host : str
        Address to bind ("0.0.0.0": every interface).
    port : int
        UDP port (0: any free one; see :attr:`port`).
    stream_hz : float
        Packets per second to each console [Hz].
    update_hz : float
        The monitor's update rate, for the consoles' information [Hz].
    sock : socket, optional
        A bound non-blocking socket to use instead (tests).

    Attributes
    ----------
    counters : dict
        ``sent``, ``spikes_sent``, ``spikes_skipped`` and the session's
        ``joins``, ``welcomes``, ``send_errors``, ``peers_dropped``
        (:class:`bonesim.net.packets.SessionServer`); :attr:`rx` holds the received
        datagrams by outcome.
    """

    def __init__(self, names, colors, params, key: bytes, host: str = "0.0.0.0",
                 port: int = DEFAULT_PORT, stream_hz: float = STREAM_HZ,
                 update_hz: float | None = None, sock=None):
        if not stream_hz > 0:
            raise ValueError(f"stream_hz must be positive, got {stream_hz}")
        self.names = list(names)
        self.k = len(self.names)
        if self.k == 0 or max_spikes(self.k) < 1:
            raise ValueError(f"cannot stream {self.k} nerves")
        colors = np.asarray(colors, dtype=int)
        if colors.shape != (self.k, 3):
            raise ValueError(f"colors must be ({self.k}, 3) for {self.k} nerves, got shape "
                             f"{colors.shape}")
        sock = sock if sock is not None else net.udp_socket(host, port)
        self.port = int(sock.getsockname()[1]) if hasattr(sock, "getsockname") else int(port)
        self.stream_hz = float(stream_hz)
        info = {"service": "nerve-monitor", "names": self.names,
                "titles": [clinical_name(n) for n in self.names],
                "colors": colors.tolist(),
                "params": asdict(params), "stream_hz": self.stream_hz,
                "update_hz": update_hz}
        self.counters = dict.fromkeys(("sent", "spikes_sent", "spikes_skipped"), 0)
        self.session = net.SessionServer(sock, key, info, stale_s=STALE_S,
                                         timeout_s=CLIENT_TIMEOUT_S, counters=self.counters,
                                         make_peer=self._new_console)
        self.t_s = math.nan
        self.updates = 0
        self.rates = np.zeros(self.k, np.float32)
        self.dist = np.full(self.k, np.inf, np.float32)
        self._spikes = _spike_ring(SPIKE_LOG)
        self._next_send = -math.inf
        self._pbuf = bytearray(net.MAX_PAYLOAD)
        self._max = max_spikes(self.k)

    @staticmethod
    def _new_console(peer) -> None:
        peer.spike_pos = 0                     # next spike to send it
        peer.number = 0                        # its next DATA packet's number

    @property
    def rx(self) -> dict:
        """Received datagrams by outcome (:data:`bonesim.net.packets.COUNTERS`)."""
        return self.session.rx

    @property
    def clients(self) -> dict:
        """Joined consoles by address."""
        return self.session.peers

    @property
    def n_clients(self) -> int:
        """Consoles joined."""
        return len(self.clients)

    @property
    def packets_sent(self) -> int:
        return self.counters["sent"]

    def add(self, t_s: float, rates, dist, spike_t, spike_n) -> None:
        """Take one monitor update: the time [s], rates [spikes/s] and
        distances [mm] of the k nerves, and the update's spikes."""
        self.t_s = float(t_s)
        self.updates += 1
        self.rates[:] = rates
        self.dist[:] = dist
        self._spikes.append(t_s=spike_t, nerve=spike_n)

    # --------------------------------------------------------------- poll
    def poll(self, now: float) -> int:
        """Receive, and send if a stream period has passed, at time ``now``
        [s]; returns the DATA packets sent."""
        for c, _ in self.session.receive(now):
            if not c.streaming:                           # its first ACK
                c.streaming = True
                c.spike_pos = self._spikes.count
        if now + 1e-6 < self._next_send or self.updates == 0:   # (float sums of periods)
            return 0
        self._next_send = max(self._next_send + 1.0 / self.stream_hz, now)
        sent = 0
        for c in self.session.expire(now):
            if not c.streaming:
                continue
            head = self._spikes.count
            if head - c.spike_pos > SPIKE_LOG:
                self.counters["spikes_skipped"] += head - SPIKE_LOG - c.spike_pos
                c.spike_pos = head - SPIKE_LOG
            while True:
                n = min(head - c.spike_pos, self._max)
                sp = self._spikes.read(c.spike_pos, c.spike_pos + n)
                size = pack_data(self._pbuf, self.t_s, self.updates, c.number, self.rates,
                                 self.dist, sp["t_s"], sp["nerve"])
                self.session.send(c, KIND_DATA, memoryview(self._pbuf)[:size])
                c.number += 1
                c.spike_pos += n
                self.counters["sent"] += 1
                self.counters["spikes_sent"] += n
                sent += 1
                if c.spike_pos >= head:
                    break
        return sent

    def stats(self) -> dict:
        return {**self.counters, "received": dict(self.rx), "consoles": len(self.clients),
                "streaming": sum(c.streaming for c in self.clients.values()),
                "port": self.port, "stream_hz": self.stream_hz}

    def close(self) -> None:
        """Say BYE to every console and close the socket."""
        self.session.bye()
        self.session.sock.close()


# ------------------------------------------------------------------- console
class MonitorConsole:
    """The monitoring technician's end: joins a :class:`MonitorServer` and
    keeps what it streams.

    Parameters
    ----------
    host : str
        The simulator's address.
    port : int
    key : bytes
    sock : socket, optional
        Bound non-blocking UDP socket (default: any local port).
    clock : callable
        Time source for :meth:`connect` and latency [s] (default monotonic).

    Attributes
    ----------
    info : dict
        The server's description (from WELCOME): ``names``, ``colors``,
        ``params``, ``stream_hz``, ``update_hz``.
    rates_hz, distance_mm : (k,) float64
        Latest values.
    t_s : float
        Monitor time of the latest data [s] (NaN before any).
    counters : dict
        ``acks_sent``, ``data``, ``lost`` (DATA packets missing from the
        numbering), ``spikes``, ``link_lost`` (times the link was lost) and
        the session's ``joins_sent``, ``welcomes``, ``byes``.
    link : bonesim.net.packets.SessionClient
        The session with the server (socket, inbox, WELCOME description).
    """

    def __init__(self, host: str, port: int, key: bytes, sock=None, clock=time.monotonic):
        self.counters = dict.fromkeys(("acks_sent", "data", "lost", "spikes", "link_lost"), 0)
        self.link = net.SessionClient(host, port, key, (KIND_DATA,), stale_s=STALE_S,
                                      join_retry_s=JOIN_RETRY_S, rejoin_s=REJOIN_S,
                                      sock=sock, what="nerve monitor",
                                      counters=self.counters)
        self.clock = clock
        self.t_s = math.nan
        self.updates = 0
        self.rates_hz = np.zeros(0)
        self.distance_mm = np.zeros(0)
        self.link_ok = False
        self._number = -1
        self._last_ack = -math.inf
        self._latency: list = []
        self._hist = _history_ring(HISTORY_CAP, 0)
        self._spikes = _spike_ring(HISTORY_CAP)
        #: Called with (spike_t, spike_nerve, t_s) for each DATA packet (clicks).
        self.on_spikes = None

    @property
    def info(self) -> dict:
        return self.link.info

    @property
    def sock(self):
        return self.link.sock

    @property
    def inbox(self) -> net.Inbox:
        return self.link.inbox

    @property
    def nonce(self) -> int:
        return self.link.nonce

    @property
    def names(self) -> list:
        return list(self.info.get("names", []))

    @property
    def titles(self) -> list:
        """The nerves' clinical names, for the screen (the server's, else
        made here from :attr:`names`)."""
        got = self.info.get("titles")
        if isinstance(got, list) and len(got) == self.n:
            return [str(x) for x in got]
        return [clinical_name(n) for n in self.names]

    @property
    def n(self) -> int:
        return len(self.names)

    def _ack(self, now: float) -> None:
        self.link.send(net.KIND_ACK, b"")
        self._last_ack = now
        self.counters["acks_sent"] += 1

    # ------------------------------------------------------------ receive
    def _welcome(self, new: bool, now: float) -> None:
        if new:                                           # a new server session
            try:
                k = len(self.info["names"])
            except (KeyError, TypeError):
                raise net.PacketError("length", "WELCOME description is not the "
                                                "monitor's JSON") from None
            self.rates_hz = np.zeros(k)
            self.distance_mm = np.full(k, np.inf)
            self._hist = _history_ring(HISTORY_CAP, k)
            self._spikes = _spike_ring(HISTORY_CAP)
            self._number = -1
        self._ack(now)

    def _data(self, p, now: float) -> None:
        d = unpack_data(p.payload)
        if len(d["rate"]) != self.n:
            raise net.PacketError("length", f"DATA for {len(d['rate'])} nerves; the "
                                            f"server announced {self.n}")
        if self._number >= 0 and d["number"] > self._number + 1:
            self.counters["lost"] += d["number"] - self._number - 1
        self._number = d["number"]
        self.counters["data"] += 1
        self._latency.append(now - p.t_s)
        if len(self._latency) > 1 << 16:
            del self._latency[:1 << 15]
        self.link.last_valid_s = now
        if d["t_s"] != self.t_s:                          # a new update: one history row
            self._hist.append(t_s=[d["t_s"]], rate=d["rate"][None], dist=d["dist"][None])
        self.t_s = d["t_s"]
        self.updates = d["updates"]
        self.rates_hz = d["rate"].astype(np.float64)
        self.distance_mm = d["dist"].astype(np.float64)
        self._spikes.append(t_s=d["spike_t"], nerve=d["spike_nerve"])
        self.counters["spikes"] += len(d["spike_t"])
        if self.on_spikes is not None:
            self.on_spikes(d["spike_t"], d["spike_nerve"], d["t_s"])

    def poll(self, now_s: float | None = None) -> None:
        """Join, receive and keep the link alive at time ``now_s`` [s]."""
        now = self.clock() if now_s is None else now_s
        for item in self.link.receive(now):
            try:
                if isinstance(item, net.Welcome):
                    self._welcome(item.new, now)
                elif self.link.welcomed:
                    self._data(item, now)
            except net.PacketError:
                self.link.reject()
        if self.link.welcomed and now - self._last_ack >= KEEPALIVE_S:
            self._ack(now)
        ok = self.link.welcomed and now - self.link.last_valid_s <= LINK_LOSS_S
        if self.link_ok and not ok:
            self.counters["link_lost"] += 1
        self.link_ok = ok

    def connect(self, timeout_s: float = 10.0) -> None:
        """Join and wait for the server's WELCOME (names and parameters known;
        data follows as the monitor updates).

        Raises
        ------
        BonesimError
            If the server does not answer in time (wrong address, port or key).
        """
        end = self.clock() + timeout_s
        while not self.link.welcomed:
            now = self.clock()
            if now > end:
                addr = self.link.addr
                raise BonesimError(f"no answer from the nerve monitor at {addr[0]}:"
                                   f"{addr[1]} within {timeout_s:g} s (check the "
                                   "address, the port, the key file (a server ignores "
                                   "joins under another key) and the firewall, and that "
                                   "the simulator serves the monitor: bonesim run "
                                   "--monitor-port)",
                                   field="HOST")
            self.poll(now)
            time.sleep(0.002)

    # ------------------------------------------------------------- output
    def history(self, window_s: float = 5.0) -> dict:
        """The last ``window_s`` seconds, as :meth:`bonesim.runtime.monitor.MonitorView.history`
        returns them (:func:`bonesim.physics.monitor_rings.read_history`)."""
        from bonesim.physics.monitor_rings import read_history

        now = 0.0 if math.isnan(self.t_s) else self.t_s
        return read_history(self._hist, self._spikes, now, self.n, window_s)

    def lines(self, width: int = 24) -> list:
        """The console's text: one line per nerve (distance, rate, a bar on a
        square-root scale, WARNING below the warning distance) and a link line."""
        p = self.info.get("params", {})
        warn = float(p.get("warn_mm", 1.0))
        top = float(p.get("max_hz", 400.0))
        out = []
        titles = self.titles
        wide = max([16] + [len(x) for x in titles])
        for c, name in enumerate(titles):
            d, r = float(self.distance_mm[c]), float(self.rates_hz[c])
            dtxt = f"{d:6.2f} mm" if d < 99.5 else "  far    "
            fill = int(round(width * math.sqrt(max(r, 0.0) / top))) if top > 0 else 0
            bar = "#" * min(fill, width) + "." * (width - min(fill, width))
            alarm = "  WARNING" if d < warn else ""
            out.append(f"{name:{wide}s} d {dtxt}  {r:6.1f}/s |{bar}|{alarm}")
        lat = np.asarray(self._latency[-1000:]) * 1e3
        lat_txt = f"latency p50 {np.percentile(lat, 50):.2f} ms" if len(lat) else "latency -"
        link = "link ok" if self.link_ok else "LINK LOST"
        out.append(f"{link}  t {self.t_s:8.2f} s  {lat_txt}  packets {self.counters['data']}"
                   f"  lost {self.counters['lost']}")
        return out

    def stats(self) -> dict:
        lat = np.asarray(self._latency) * 1e3
        pct = ({q: round(float(np.percentile(lat, v)), 3)
                for q, v in (("p50", 50), ("p99", 99), ("max", 100))} if len(lat) else {})
        data = self.counters["data"]
        return {"names": self.names, "packets": dict(self.inbox.counters), **self.counters,
                "loss_fraction": round(self.counters["lost"] / max(data + self.counters[
                    "lost"], 1), 5),
                "latency_ms": pct, "t_s": None if math.isnan(self.t_s) else self.t_s,
                "updates": self.updates, "rates_hz": [round(float(x), 2)
                                                      for x in self.rates_hz],
                "distance_mm": [round(float(x), 3) if math.isfinite(x) else None
                                for x in self.distance_mm],
                "link_ok": self.link_ok}

    def close(self) -> None:
        """Say BYE (if in a session) and close the socket."""
        self.link.close()


# ----------------------------------------------------------------------- CLI
#: Console refresh period [s] (terminal redraw or printed block).
REFRESH_S = 0.1


def _console_clicks(con: MonitorConsole, wav=None):
    """A click per received spike, on the sound device (or a silent sink that
    still writes ``wav``). The click delay covers two stream periods."""
    from bonesim.sound.clicks import DELAY_S, ClickSynth
    from bonesim.sound.clicks import warmup as clicks_warmup
    from bonesim.sound.drill import SAMPLE_RATE, WavRecorder, open_output

    clicks_warmup()
    stream_hz = float(con.info.get("stream_hz") or STREAM_HZ)
    synth = ClickSynth(SAMPLE_RATE, max(con.n, 1), delay_s=DELAY_S + 2.0 / stream_hz)
    recorder = WavRecorder(wav, SAMPLE_RATE) if wav else None
    out = open_output(synth, recorder=recorder)

    def on_spikes(t, nerve, now_t):
        synth.sync(now_t)                      # anchors the clock before any schedule
        if len(t):
            synth.schedule(t, nerve)

    con.on_spikes = on_spikes
    return synth, out, recorder


def run_console(args) -> dict:
    """The monitoring technician's console (``bonesim monitor HOST``,
    :mod:`bonesim.cli.monitor`): connect, show the readings until the
    simulator stops or ``args.duration`` [s] ends, and return the link's
    statistics (:meth:`MonitorConsole.stats`, with ``clicks`` when sounded)."""
    import select
    import sys

    key = net.load_key(args.key_file)
    con = MonitorConsole(args.host, args.port, key)
    synth = out = recorder = None
    tty = sys.stdout.isatty() and not args.json
    try:
        con.connect(args.timeout)
        print(f"bonesim: nerve monitor of {args.host}:{args.port}: "
              f"{', '.join(con.titles)}", file=sys.stderr)
        if not args.no_sound or args.wav:
            synth, out, recorder = _console_clicks(con, args.wav)
        end = math.inf if args.duration is None else con.clock() + args.duration
        every = REFRESH_S if tty else args.every
        next_print = con.clock() + every
        drawn = 0
        byes = con.counters["byes"]
        try:
            while con.clock() < end and con.counters["byes"] == byes:
                con.poll()
                now = con.clock()
                if not args.json and every > 0 and now >= next_print:
                    lines = con.lines()
                    if tty and drawn:
                        sys.stdout.write(f"\x1b[{drawn}F\x1b[J")     # redraw in place
                    print("\n".join(lines), flush=True)
                    drawn = len(lines)
                    next_print = now + every
                # sleep until a datagram comes (or a keep-alive, print or end is due)
                select.select([con.sock], [], [], min(KEEPALIVE_S / 2, max(end - now, 0.0)))
        except KeyboardInterrupt:
            pass
        s = con.stats()
        if synth is not None:
            s["clicks"] = {"scheduled": synth.scheduled, "late": synth.late,
                           "dropped": synth.dropped, "sound": out.notice is None}
    finally:
        if out is not None:
            out.close()
        if recorder is not None:
            recorder.close()
        con.close()
    return s
