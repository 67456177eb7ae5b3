"""Haptic tutoring and haptic playback.

The trainee's device is driven by a low-gain position controller toward the
instructor's tool plus the instructor's own force (see ``SPEC.md``,
"Training features beyond a cadaver lab")::

    F_trainee = K_p (P_instructor - P_trainee) + F_instructor

clamped to the trainee device's force limit (:func:`tutor_force`). The
instructor's force carries the bone's contact force, the burr's drag and its
vibration; the weak spring keeps the trainee's tool near the instructor's
without masking them. Where the instructor's state comes from is a
:class:`Source`:

:class:`NetworkSource`
    live, from an instructor's :class:`TutorServer` over authenticated UDP
    (:mod:`bonesim.net`): ``bonesim tutor serve`` / ``bonesim tutor join``.
:class:`RecordingSource`
    a recorded session file (haptic playback): ``bonesim tutor playback``.

A :class:`Trainee` runs the servo tick at 1 kHz: poll the source, read the
device, compute the force, write it. When the source goes quiet (network
loss, end of a recording) the force ramps to zero within
:data:`LOSS_S` + :data:`RAMP_S` = 45 ms of the last valid data, and
:attr:`Trainee.link_lost` / the HUD text say so; when data returns the force
fades back in over :data:`RECOVER_S`.

Wire protocol (packets of :mod:`bonesim.net`)
---------------------------------------------
1. The trainee draws a random nonce and sends ``JOIN`` (header nonce = its
   own nonce) every :data:`JOIN_RETRY_S` until welcomed.
2. The server answers ``WELCOME`` (nonce = the trainee's) whose payload is
   the server's nonce for this trainee (u64) and a JSON description of the
   session (case, burrs, grid size). A replayed JOIN therefore earns at most
   one small WELCOME: streaming starts only after
3. the trainee's first ``ACK`` carrying the server's nonce. The trainee keeps
   ACKing every :data:`KEEPALIVE_S`; the server forgets a trainee that is
   silent for :data:`CLIENT_TIMEOUT_S`.
4. The server sends one ``STATE`` packet (:data:`KIND_STATE`) per haptic
   sample to every trainee: the latest sample's pose, force and drill state
   (:data:`STATE`), then up to :data:`MAX_REMOVALS` voxel removals.

Voxel removals must all arrive. The server keeps the current epoch's removals
in a log (an epoch starts at a case reset; the log of a server started
mid-session begins with a snapshot of the voxels already gone). Every STATE
packet names the log index of its first removal and the log's length; the
trainee applies only the next contiguous removals and, seeing a gap, sends
an ACK flagged :data:`FLAG_NACK` with the count it holds. The server then
resends from that index (go-back-N). A new epoch, or a new server, restarts
the log and the trainee's replica.

Every datagram is authenticated and checked (nonce, sequence, staleness) by
:class:`bonesim.net.Inbox`; anything else is dropped and counted, and
changes nothing.
"""
from __future__ import annotations

import math
import multiprocessing as mp
import struct
import time

import numpy as np
from numba import njit

from . import events, net
from .errors import BonesimError
from .net import udp_socket
from .shared import die_with_parent, end_process, start_process, wait_ready

# ----------------------------------------------------------------- constants
#: Controller spring K_p [N/mm]. Half the stable stiffness of a 3D Systems
#: Touch's weakest axis (0.39 N/mm), so the coupling is stable on the usual
#: trainee device even with the hand's own stiffness added. Drilling forces
#: are 0.5-3 N: the spring stays below the instructor's force until the tools
#: are 2.5-15 mm apart, so what the trainee feels is dominated by the
#: instructor's contact, drag and vibration (the thesis: "small enough not to
#: interfere with the high-frequency components"), while a 10 mm lag already
#: pulls with 2 N. With the default simulated hand (0.15 kg, 8 N s/m,
#: 0.02 N/mm) the loop is well damped (damping ratio 0.7, natural frequency
#: 6 Hz), and free-hand motion is tracked to within a few millimetres.
KP_N_PER_MM = 0.2
#: No valid instructor data for this long: the link is lost [s].
LOSS_S = 0.020
#: After the loss, the force ramps linearly to zero over this [s]
#: (zero by LOSS_S + RAMP_S = 45 ms, inside the 50 ms safety bound).
RAMP_S = 0.025
#: When data returns the force fades back in over this, so the spring does
#: not snap the hand toward an instructor who moved on [s].
RECOVER_S = 0.2
#: Trainee servo rate [Hz].
SERVO_HZ = 1000.0
#: Default UDP port of ``bonesim tutor serve``.
DEFAULT_PORT = net.DEFAULT_PORT
#: Packets delayed more than this beyond the fastest delivery are dropped [s].
STALE_S = 0.1
#: A not-yet-welcomed trainee repeats its JOIN this often [s].
JOIN_RETRY_S = 0.25
#: A trainee acknowledges (keep-alive) this often [s].
KEEPALIVE_S = 0.05
#: A trainee repeats a NACK for the same count at most this often [s].
NACK_HOLD_S = 0.02
#: A welcomed trainee that hears nothing valid for this long joins again [s].
REJOIN_S = 1.0
#: The server forgets a trainee silent for this long [s].
CLIENT_TIMEOUT_S = 2.0

#: Tutoring's data packet kind (services number their kinds from 16).
KIND_STATE = 16
#: ACK flag: the trainee found a gap in the removals (go back).
FLAG_NACK = 1

#: STATE payload, fixed part: sample time [s], tool centre [mm] (3), axis (3),
#: force sent to the instructor's device [N] (3), speed [rpm], normal force
#: magnitude [N], immersed volume [mm^3], epoch, buttons, drill, direction,
#: burr, (pad), removal log length, first removal's log index, removals here.
STATE = struct.Struct("<d3d3d3ddddiIBbBBQQH")
#: One removal on the wire: voxel (i, j, k) as int32.
REMOVAL_BYTES = 12
#: Removals that fit in one STATE packet.
MAX_REMOVALS = (net.MAX_PAYLOAD - STATE.size) // REMOVAL_BYTES
#: ACK payload: removals held (u64), epoch (i32).
ACK = struct.Struct("<Qi")
#: A :attr:`Source.changes` row saying "back to the initial tissue".
RESET_IJK = np.full((1, 3), -1, dtype=np.int32)


# ----------------------------------------------------------------- controller
@njit(cache=True, nogil=True)
def tutor_force(p_instr, p_trainee, f_instr, kp_n_per_mm, max_force_n, gain, out):
    """The trainee's force, in place (allocation-free).

    ``out = gain * (kp (p_instr - p_trainee) + f_instr)``, scaled down to
    ``max_force_n`` if longer; zero if any input is not finite.

    Parameters
    ----------
    p_instr, p_trainee : (3,) float64
        Instructor's and trainee's tool centres [mm].
    f_instr : (3,) float64
        Force the instructor's device renders [N].
    kp_n_per_mm : float
        Spring gain K_p [N/mm].
    max_force_n : float
        Trainee device's force limit [N].
    gain : float
        Link gain in [0, 1] (:func:`link_gain`).
    out : (3,) float64
        Receives the force [N].

    Returns
    -------
    float
        Magnitude of ``out`` [N].
    """
    s = 0.0
    for a in range(3):
        v = gain * (kp_n_per_mm * (p_instr[a] - p_trainee[a]) + f_instr[a])
        out[a] = v
        s += v * v
    n = math.sqrt(s)
    if not n <= max_force_n:                      # longer than allowed, or NaN
        if math.isfinite(n) and n > 0.0 and max_force_n >= 0.0:
            k = max_force_n / n
            for a in range(3):
                out[a] *= k
            return max_force_n
        for a in range(3):
            out[a] = 0.0
        return 0.0
    return n


def link_gain(age_s: float, prev_gain: float, dt_s: float) -> float:
    """Force gain from the age of the freshest valid data.

    1 while the data is younger than :data:`LOSS_S`, then falling linearly to
    0 over :data:`RAMP_S`; after a loss it rises back by ``dt_s / RECOVER_S``
    per tick, never above the ramp.

    Parameters
    ----------
    age_s : float
        Time since the last valid data [s] (``inf`` if none yet).
    prev_gain : float
        The previous tick's gain.
    dt_s : float
        Time since the previous tick [s].
    """
    if age_s <= LOSS_S:
        ramp = 1.0
    elif age_s < LOSS_S + RAMP_S:
        ramp = (LOSS_S + RAMP_S - age_s) / RAMP_S
    else:
        ramp = 0.0                                    # also NaN ages
    up = prev_gain + max(dt_s, 0.0) / RECOVER_S
    return ramp if ramp < up else (up if up < 1.0 else 1.0)


# ------------------------------------------------------------ instructor state
class InstructorState:
    """The instructor's latest sample as a trainee sees it (preallocated).

    Attributes
    ----------
    t_s : float
        Instructor's loop time of the sample [s].
    pos_mm, axis, force_n : (3,) float64
        Tool centre [mm], drill axis, force on the instructor's device [N].
    speed_rpm, mag_n, volume_mm3 : float
    epoch, buttons, drill, direction, burr : int
    valid : bool
        A sample has been received.
    """

    def __init__(self):
        self.t_s = math.nan
        self.pos_mm = np.zeros(3)
        self.axis = np.array([0.0, 0.0, -1.0])
        self.force_n = np.zeros(3)
        self.speed_rpm = 0.0
        self.mag_n = 0.0
        self.volume_mm3 = 0.0
        self.epoch = 0
        self.buttons = 0
        self.drill = 0
        self.direction = 1
        self.burr = 0
        self.valid = False


def pack_state(buf, t_s, pos, axis, force, speed, mag, volume, epoch, buttons, drill,
               direction, burr, log_len, first, ijk) -> int:
    """Write a STATE payload into ``buf``; returns its length [bytes].

    ``ijk`` is a (k, 3) int32 array of removals (k <= :data:`MAX_REMOVALS`)
    starting at log index ``first``.
    """
    k = len(ijk)
    STATE.pack_into(buf, 0, t_s, pos[0], pos[1], pos[2], axis[0], axis[1], axis[2],
                    force[0], force[1], force[2], speed, mag, volume, epoch, buttons,
                    drill, direction, burr, 0, log_len, first, k)
    end = STATE.size + k * REMOVAL_BYTES
    if k:
        buf[STATE.size:end] = np.ascontiguousarray(ijk, dtype="<i4").data.cast("B")
    return end


def unpack_state(payload, st: InstructorState):
    """Read a STATE payload into ``st``.

    Returns
    -------
    log_len, first : int
    ijk : (k, 3) int32
        The removals carried (a read-only view of ``payload``).

    Raises
    ------
    bonesim.net.PacketError
        ``length`` if the payload size disagrees with its removal count.
    """
    if len(payload) < STATE.size:
        raise net.PacketError("length", f"STATE payload of {len(payload)} bytes, the fixed "
                                        f"part alone is {STATE.size}")
    (t, px, py, pz, ax, ay, az, fx, fy, fz, speed, mag, vol, epoch, buttons, drill,
     direction, burr, _, log_len, first, k) = STATE.unpack_from(payload, 0)
    if len(payload) != STATE.size + k * REMOVAL_BYTES:
        raise net.PacketError("length", f"STATE says {k} removals, the payload holds "
                                        f"{(len(payload) - STATE.size) / REMOVAL_BYTES:g}")
    vals = (t, px, py, pz, ax, ay, az, fx, fy, fz, speed, mag, vol)
    if not all(math.isfinite(v) for v in vals):
        raise net.PacketError("length", "STATE carries a non-finite number")
    st.t_s = t
    p, a, f = st.pos_mm, st.axis, st.force_n
    p[0], p[1], p[2] = px, py, pz
    a[0], a[1], a[2] = ax, ay, az
    f[0], f[1], f[2] = fx, fy, fz
    st.speed_rpm, st.mag_n, st.volume_mm3 = speed, mag, vol
    st.epoch, st.buttons, st.drill, st.direction, st.burr = epoch, buttons, drill, \
        direction, burr
    st.valid = True
    ijk = np.frombuffer(payload, dtype="<i4", count=3 * k, offset=STATE.size).reshape(k, 3)
    return log_len, first, ijk


class RemovalLog:
    """The current epoch's removals, indexed from 0, growing (server side)."""

    def __init__(self, capacity: int = 1 << 14):
        self.ijk = np.zeros((capacity, 3), np.int32)
        self.n = 0

    def clear(self) -> None:
        self.n = 0

    def extend(self, ijk) -> None:
        k = len(ijk)
        if self.n + k > len(self.ijk):
            cap = len(self.ijk)
            while cap < self.n + k:
                cap *= 2
            grown = np.zeros((cap, 3), np.int32)
            grown[:self.n] = self.ijk[:self.n]
            self.ijk = grown
        self.ijk[self.n:self.n + k] = ijk
        self.n += k


def removed_voxels(initial_density, density, bricks) -> np.ndarray:
    """Voxels present initially and gone now, as (n, 3) int32."""
    b, o = np.nonzero((initial_density > 0) & (density <= 0))
    out = np.empty((len(b), 3), np.int32)
    out[:, 0] = bricks[b, 0] * 8 + (o >> 6)
    out[:, 1] = bricks[b, 1] * 8 + ((o >> 3) & 7)
    out[:, 2] = bricks[b, 2] * 8 + (o & 7)
    return out


def session_info(model, burrs=()) -> dict:
    """What a trainee needs to rebuild the instructor's tissue (WELCOME)."""
    case = model.case
    return {"case": getattr(case, "name", model.name),
            "case_path": str(getattr(case, "manifest", "")) or None,
            "burrs": [model.burr.name] + [b.name for b in burrs],
            "n_bricks": int(model.grid.n_bricks),
            "spacing_mm": float(model.grid.spacing_mm)}


# -------------------------------------------------------------------- server
class Streamer:
    """The instructor side of tutoring, one :meth:`tick` at a time.

    It reads the haptic loop's ``samples`` and ``removed`` rings (in shared
    memory when run by :class:`TutorServer`), answers JOINs and ACKs, and
    sends each streaming trainee a STATE packet per new sample.

    Parameters
    ----------
    sock : socket.socket
        Bound, non-blocking UDP socket (anything with ``sendto`` and
        ``recvfrom_into``).
    key : bytes
    samples, removed : events.Ring
        The loop's rings.
    info : dict
        Session description sent in WELCOME (:func:`session_info`).
    density, initial_density, bricks : ndarray, optional
        Live and initial tissue density and the brick coordinates: with them
        the log starts with the voxels already removed when the server
        starts (a server started mid-session).

    Attributes
    ----------
    counters : dict
        ``sent``, ``removals_sent``, ``nacks``, ``go_backs`` and the
        session's ``joins``, ``welcomes``, ``send_errors``, ``peers_dropped``
        (:class:`bonesim.net.SessionServer`); :attr:`rx` holds the received
        datagrams by outcome.
    """

    def __init__(self, sock, key: bytes, samples: events.Ring, removed: events.Ring,
                 info: dict, density=None, initial_density=None, bricks=None):
        self.samples = samples
        self.removed = removed
        self.log = RemovalLog()
        self.counters = dict.fromkeys(("sent", "removals_sent", "nacks", "go_backs"), 0)
        self.session = net.SessionServer(sock, key, info, stale_s=STALE_S,
                                         timeout_s=CLIENT_TIMEOUT_S, counters=self.counters,
                                         make_peer=self._new_trainee)
        self._pbuf = bytearray(net.MAX_PAYLOAD)
        self._sf = samples.fields
        self._smask = samples.capacity - 1
        n = samples.count
        self.s_pos = n
        self.epoch = int(self._sf["epoch"][(n - 1) & self._smask]) if n else 0
        self.t_done = float(self._sf["t_s"][(n - 1) & self._smask]) if n else -math.inf
        # cursor first, then the snapshot (re-listing a voxel is harmless)
        self.r_pos = removed.count
        if density is not None:
            self.log.extend(removed_voxels(initial_density, density, bricks))

    @staticmethod
    def _new_trainee(peer) -> None:
        peer.send_from = 0                     # next log index to send it
        peer.acked = 0                         # removals it holds
        peer.last_sent_sample = -1

    @property
    def clients(self) -> dict:
        """Joined trainees by address (:class:`bonesim.net.Peer`)."""
        return self.session.peers

    @property
    def rx(self) -> dict:
        """Received datagrams by outcome (:data:`bonesim.net.COUNTERS`)."""
        return self.session.rx

    # ------------------------------------------------------------- inputs
    def _pump(self) -> None:
        """Take the samples and removals published since the last call."""
        n = self.samples.count
        if n == self.s_pos:
            return
        start = max(self.s_pos, n - self.samples.capacity + 1)
        ep = self._sf["epoch"]
        idx = np.arange(start, n) & self._smask
        epochs = ep[idx]
        t_new = self._sf["t_s"][idx]
        t_last = float(t_new[-1])
        boundary = -math.inf
        changed = np.flatnonzero(epochs != np.concatenate(([self.epoch], epochs[:-1])))
        if len(changed):                         # a case reset: new log
            boundary = float(t_new[changed[-1]])
            self.epoch = int(epochs[-1])
            self.log.clear()
            for c in self.clients.values():
                c.send_from = 0
                c.acked = 0
        # removals of completed steps only (their sample is out): t <= t_last
        r_n = self.removed.count
        if r_n > self.r_pos:
            rec = self.removed.read(self.r_pos, r_n)
            t = rec["t_s"]
            done = int(np.searchsorted(t, t_last, side="right"))
            first = int(np.searchsorted(t[:done], boundary, side="left"))
            if done > first:
                self.log.extend(rec["ijk"][first:done])
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
        sent = 0
        for c in self.session.expire(now):
            if not c.streaming:
                continue
            pending = self.log.n - c.send_from
            if head == c.last_sent_sample and pending <= 0:
                continue
            k = min(max(pending, 0), MAX_REMOVALS)
            n = pack_state(self._pbuf, f["t_s"][q], f["pos_mm"][q], f["axis"][q],
                           f["force_n"][q], f["speed_rpm"][q], f["mag_n"][q],
                           f["volume_mm3"][q], self.epoch, int(f["buttons"][q]),
                           int(f["drill"][q]), int(f["direction"][q]), int(f["burr"][q]),
                           self.log.n, c.send_from,
                           self.log.ijk[c.send_from:c.send_from + k])
            self.session.send(c, KIND_STATE, memoryview(self._pbuf)[:n])
            c.send_from += k
            c.last_sent_sample = head
            self.counters["sent"] += 1
            self.counters["removals_sent"] += k
            sent += 1
        return sent

    def bye(self) -> None:
        """Tell every trainee the session ends."""
        self.session.bye()

    def stats(self) -> dict:
        return {**self.counters, "received": dict(self.rx), "clients": len(self.clients),
                "streaming": sum(c.streaming for c in self.clients.values()),
                "log_removals": self.log.n, "epoch": self.epoch}


# server process ------------------------------------------------------------
(SV_READY, SV_PORT, SV_QUIT, SV_DONE, SV_CLIENTS, SV_SENT, SV_REMOVALS, SV_NACKS,
 SV_GO_BACKS, SV_LOG, SV_TICKS, SV_ERROR) = range(12)
N_SV = 16


def _serve_main(handle, host, port, key, rate_hz, info, initial_density, bricks, status,
                conn) -> None:
    """Body of the server process: attach to the loop, stream until told to quit."""
    from .haptic_loop import attach

    die_with_parent()
    sh, rings = attach(handle)
    sock = None
    stats = {}
    try:
        try:
            sock = udp_socket(host, port)
        except BonesimError as exc:
            conn.send({"error": str(exc)})
            status[SV_ERROR] = 1.0
            return
        streamer = Streamer(sock, key, rings["samples"], rings["removed"], info,
                            density=sh.arrays["density"], initial_density=initial_density,
                            bricks=bricks)
        status[SV_PORT] = sock.getsockname()[1]
        status[SV_READY] = 1.0
        period = 1.0 / rate_hz
        clock = time.monotonic
        deadline = clock()
        ticks = 0
        while status[SV_QUIT] == 0.0:
            streamer.tick(clock())
            ticks += 1
            if ticks % 64 == 0:
                c = streamer.counters
                status[SV_CLIENTS] = len(streamer.clients)
                status[SV_SENT] = c["sent"]
                status[SV_REMOVALS] = c["removals_sent"]
                status[SV_NACKS] = c["nacks"]
                status[SV_GO_BACKS] = c["go_backs"]
                status[SV_LOG] = streamer.log.n
                status[SV_TICKS] = ticks
            deadline += period
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest)
            elif rest < -10 * period:                 # fell far behind: do not burst
                deadline = clock()
        streamer.bye()
        stats = streamer.stats()
        stats["ticks"] = ticks
    finally:
        try:
            conn.send(stats)
        except (OSError, ValueError):
            pass
        if sock is not None:
            sock.close()
        rings.clear()
        sh.close()
        status[SV_DONE] = 1.0


class TutorServer:
    """Streams a running :class:`~bonesim.haptic_loop.HapticLoop` to trainees
    from its own process, attached to the loop's shared memory, so that
    neither the loop nor a window in the main process delays sending.

    Parameters
    ----------
    loop : HapticLoop
        Started or about to be (its rings must exist: the shared memory).
    key : bytes
        Shared packet key (:func:`bonesim.net.load_key`).
    host : str
        Address to bind ("0.0.0.0": every interface; "127.0.0.1": local only).
    port : int
        UDP port (0: any free one, see :attr:`port`).
    rate_hz : float
        Send rate [Hz] (the haptic rate).
    """

    def __init__(self, loop, key: bytes, host: str = "0.0.0.0", port: int = DEFAULT_PORT,
                 rate_hz: float = SERVO_HZ):
        self.loop = loop
        self.key = bytes(key)
        self.host = host
        self.port = int(port)
        self.rate_hz = float(rate_hz)
        self._proc = None
        self._conn = None
        self._status = None
        self.final: dict = {}

    def start(self, timeout_s: float = 30.0) -> "TutorServer":
        ctx = mp.get_context("spawn")
        self._status = ctx.RawArray("d", N_SV)
        mine, theirs = ctx.Pipe(duplex=False)
        model = self.loop.model
        burrs = [b for b in self.loop.burrs if b is not None]
        self._proc = start_process(
            _serve_main, "bonesim-tutor-server",
            (self.loop.handle, self.host, self.port, self.key, self.rate_hz,
             session_info(model, burrs), np.asarray(model.grid.density),
             np.asarray(model.grid.bricks), self._status, theirs))
        theirs.close()
        self._conn = mine
        got = wait_ready(self._proc, lambda: self._status[SV_READY] != 0.0, timeout_s,
                         failed=lambda: self._status[SV_ERROR] != 0.0)
        if got == "exited":
            msg = self._conn.recv() if self._conn.poll(1.0) else {}
            self.stop()
            raise BonesimError(msg.get("error", "the tutoring server process exited "
                                                "during start-up"))
        if got == "timeout":
            self.stop()
            raise BonesimError("the tutoring server did not start in time")
        self.port = int(self._status[SV_PORT])
        return self

    def status(self) -> dict:
        """Live figures (refreshed every 64 ticks)."""
        s = self._status
        return {"clients": int(s[SV_CLIENTS]), "sent": int(s[SV_SENT]),
                "removals_sent": int(s[SV_REMOVALS]), "nacks": int(s[SV_NACKS]),
                "go_backs": int(s[SV_GO_BACKS]), "log_removals": int(s[SV_LOG]),
                "ticks": int(s[SV_TICKS])}

    def stop(self, timeout_s: float = 5.0) -> dict:
        """Say BYE to the trainees, stop the process; returns its final stats."""
        if self._proc is None:
            return self.final
        self._status[SV_QUIT] = 1.0
        if self._conn.poll(timeout_s):
            try:
                self.final = self._conn.recv()
            except EOFError:
                pass
        end_process(self._proc, timeout_s)
        self._proc = None
        self._conn.close()
        return self.final

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


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

        from .model import load_model

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


# ------------------------------------------------------------------- trainee
class Trainee:
    """The trainee's servo: source -> controller -> device, one tick at a time.

    Parameters
    ----------
    source : Source
    device : Device
        The trainee's device (e.g. :class:`bonesim.devices.SimulatedHandDevice`).
        A device with a ``place`` method is placed at the instructor's tool
        when the first sample arrives (a simulated hand picks up the stylus).
    kp_n_per_mm : float
        Controller gain K_p [N/mm].
    max_force_n : float, optional
        Force limit [N]; default the device's ``caps.max_force_n``.

    Attributes
    ----------
    force_n : (3,) float64
        The force last written to the device [N].
    gain : float
        Link gain (1 with fresh data, 0 after a loss).
    link_lost : bool
        No valid data for :data:`LOSS_S`.
    released : bool
        :meth:`release` was called: the force ramps out whatever comes.
    """

    def __init__(self, source: Source, device, kp_n_per_mm: float = KP_N_PER_MM,
                 max_force_n: float | None = None):
        if not kp_n_per_mm >= 0:
            raise ValueError("kp_n_per_mm must be >= 0")
        self.source = source
        self.device = device
        self.kp = float(kp_n_per_mm)
        self.max_force_n = float(device.caps.max_force_n if max_force_n is None
                                 else max_force_n)
        if not math.isfinite(self.max_force_n):
            raise BonesimError(f"the trainee device {device.caps.name!r} renders no force; "
                               "tutoring needs a force-feedback device")
        self.force_n = np.zeros(3)
        self.gain = 0.0
        self.link_lost = True
        self.placed = not hasattr(device, "place")
        self._released_at = math.nan
        self.ticks = 0
        self.lost_events = 0
        self._t0 = math.nan
        self._last = math.nan
        self.err = _LatencyLog()                      # tracking error [mm]
        self.fmag = _LatencyLog()
        self.device_pos = np.zeros(3)

    @property
    def released(self) -> bool:
        return self._released_at == self._released_at

    def release(self, now_s: float) -> None:
        """Let go of the trainee's device: from ``now_s`` [s] the force ramps
        to zero over :data:`RAMP_S`, as after a link loss, while the source
        still sends (the trainee quit mid-session)."""
        if not self.released:
            self._released_at = float(now_s)

    @property
    def hud_text(self) -> str:
        """One line for the trainee's display."""
        if self.link_lost:
            return self.source.lost_text
        if self.released:
            return "RELEASED"
        st = self.source.state
        return (f"following instructor  |F| {math.sqrt(self.force_n @ self.force_n):4.2f} N"
                f"  drill {'on' if st.drill else 'off'}")

    def tick(self, now_s: float) -> np.ndarray:
        """One servo tick at trainee time ``now_s`` [s]; returns the force written."""
        if self._t0 != self._t0:
            self._t0 = now_s
            self._last = now_s
        src = self.source
        src.poll(now_s)
        st = src.state
        if not self.placed and st.valid:
            self.device.place(st.pos_mm)
            self.placed = True
        r = self.device.read(now_s - self._t0)
        last = src.last_valid_s
        age = now_s - last if last == last else math.inf
        rel = self._released_at
        gain_age = age if rel != rel else max(age, LOSS_S + now_s - rel)
        self.gain = link_gain(gain_age, self.gain, now_s - self._last)
        lost = age > LOSS_S
        if lost and not self.link_lost:
            self.lost_events += 1
        self.link_lost = lost
        m = tutor_force(st.pos_mm, r.pos_mm, st.force_n, self.kp, self.max_force_n,
                        self.gain if st.valid else 0.0, self.force_n)
        self.device.write_force(self.force_n)
        self.device_pos[:] = r.pos_mm
        if not lost and st.valid:
            d = st.pos_mm - r.pos_mm
            self.err.add(math.sqrt(d @ d))
        self.fmag.add(m)
        self._last = now_s
        self.ticks += 1
        return self.force_n

    def run(self, duration_s: float, rate_hz: float = SERVO_HZ, clock=time.monotonic,
            until=None, on_tick=None) -> dict:
        """Tick at ``rate_hz`` for ``duration_s`` [s] (or until ``until()`` is
        true), calling ``on_tick(self)`` after each tick."""
        period = 1.0 / rate_hz
        t_end = clock() + duration_s
        deadline = clock()
        while True:
            now = clock()
            if now >= t_end or (until is not None and until()):
                break
            self.tick(now)
            if on_tick is not None:
                on_tick(self)
            deadline += period
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest)
            elif rest < -10 * period:
                deadline = clock()
        return self.stats()

    def stats(self) -> dict:
        """JSON-ready figures: ticks, link, tracking error [mm], force [N], source's."""
        e = self.err.values()
        f = self.fmag.values()
        out = {"ticks": self.ticks, "link_lost": self.link_lost,
               "link_lost_events": self.lost_events, "kp_n_per_mm": self.kp,
               "max_force_n": self.max_force_n}
        if len(e):
            out["tracking_error_mm"] = {"p50": round(float(np.percentile(e, 50)), 4),
                                        "p99": round(float(np.percentile(e, 99)), 4),
                                        "max": round(float(e.max()), 4), "n": int(len(e))}
        if len(f):
            out["force_n"] = {"mean": round(float(f.mean()), 4),
                              "max": round(float(f.max()), 4)}
        out.update(self.source.stats())
        return out

    def follow(self, duration_s: float = math.inf, stop=None, on_tick=None) -> dict:
        """Run until the source ends, ``duration_s`` [s] passes or ``stop()``
        is true (or Ctrl+C), then let the force ramp out (:meth:`release`
        if the source still sends); returns
        :meth:`stats` with the final HUD line under ``"hud"``."""
        src = self.source
        try:
            try:
                self.run(duration_s, on_tick=on_tick,
                         until=lambda: src.ended or (stop is not None and stop()))
            except KeyboardInterrupt:
                pass
            if not src.ended:
                self.release(time.monotonic())
            self.run(LOSS_S + RAMP_S + 0.01, on_tick=on_tick)
        except KeyboardInterrupt:
            pass
        s = self.stats()
        s["hud"] = self.hud_text
        return s

    def close(self) -> None:
        self.force_n[:] = 0.0
        try:
            self.device.write_force(self.force_n)
        finally:
            self.source.close()


def warmup() -> None:
    """Compile the controller (cached on disk after the first run)."""
    z = np.zeros(3)
    tutor_force(z, z, z, KP_N_PER_MM, 1.0, 1.0, np.zeros(3))


# ----------------------------------------------------------------------- CLI
