"""Haptic tutoring's constants and wire format: the instructor state on the wire,
the tissue-event log, the session description.

Wire protocol (packets of :mod:`bonesim.net.packets`)
---------------------------------------------
1. The trainee draws a random nonce and sends ``JOIN`` (header nonce = its
   own nonce) every :data:`JOIN_RETRY_S` until welcomed.
2. The server answers ``WELCOME`` (nonce = the trainee's) whose payload is
   the server's nonce for this trainee (u64) and a JSON description of the
   session (case, burrs, grid size, ``tissue_version``: the version of the
   tissue-event record it streams, :data:`bonesim.engine.events.TISSUE_EVENT_VERSION`).
   A replayed JOIN therefore earns at most one small WELCOME: streaming
   starts only after
3. the trainee's first ``ACK`` carrying the server's nonce. The trainee keeps
   ACKing every :data:`KEEPALIVE_S`; the server forgets a trainee that is
   silent for :data:`CLIENT_TIMEOUT_S`.
4. The server sends one ``STATE`` packet (:data:`KIND_STATE`) per haptic
   sample to every trainee: the latest sample's pose, force and drill state
   and the record version (:data:`STATE`), then up to :data:`MAX_EVENTS`
   tissue events (:data:`RECORD`: the columns of
   :data:`bonesim.engine.events.TISSUE_FIELDS`, packed, little-endian). A trainee
   behind by more than one packet gets up to :data:`MAX_BURST` packets a
   sample until it has caught up.

The tissue travels as the one tissue-event stream (:mod:`bonesim.engine.events`):
removals, contacts and injuries, resets, burr changes, body splits and
poses. Every event must arrive, in order. The server keeps the current
epoch's events in a :class:`TissueLog` that always begins with a ``RESET``
record: a ``RESET`` in the haptic loop's stream starts a new log (and a new
epoch, the reset's ``n``), and the log of a server started mid-session begins
with a snapshot of the tissue (:func:`tissue_snapshot`: a ``RESET``, the
splits and poses of the bodies, the voxels already removed). Applying a log
from index 0 to a :class:`~bonesim.engine.replica.TissueReplica` of the case gives
the instructor's tissue. Every STATE packet names its log's epoch, the log
index of its first event and the log's length; the trainee applies only the
next contiguous events and, seeing a gap, sends an ACK flagged
:data:`FLAG_NACK` with the count it holds. The server then resends from that
index (go-back-N). A new epoch, or a new server, restarts the count; the
log's leading ``RESET`` restarts the trainee's replica.

A trainee refuses a record version it does not know: a WELCOME announcing
another ``tissue_version`` and a STATE packet carrying another version
raise :class:`~bonesim.errors.BonesimError` naming the packet.

Every datagram is authenticated and checked (nonce, sequence, staleness) by
:class:`bonesim.net.packets.Inbox`; anything else is dropped and counted, and
changes nothing.
"""
from __future__ import annotations

import math
import struct

import numpy as np

from bonesim.engine import events
from bonesim.net import packets as net
from bonesim.engine.bodies import IDENTITY_POSE

__all__ = ["KP_N_PER_MM", "LOSS_S", "RAMP_S", "RECOVER_S", "SERVO_HZ", "DEFAULT_PORT",
           "STALE_S", "JOIN_RETRY_S", "KEEPALIVE_S", "NACK_HOLD_S", "REJOIN_S",
           "CLIENT_TIMEOUT_S", "GLOSSARY", "KIND_STATE", "FLAG_NACK", "STATE", "RECORD",
           "MAX_EVENTS",
           "MAX_BURST", "ACK", "InstructorState", "pack_state", "unpack_state",
           "check_tissue_version", "TissueLog", "tissue_snapshot", "session_info"]

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
#: One line for each word the tutoring summaries and the HUD show.
GLOSSARY = {
    "stale": f"stale: a packet more than {STALE_S * 1e3:.0f} ms older on arrival than the "
             "link's usual delay (held up by a busy machine or network), dropped: the "
             "trainee follows only fresh data",
    "go-back": "go-back: a trainee missed tissue events and asked for them again; the "
               "instructor resent its event log from the first one missing",
    "link lost": f"link lost: no valid instructor data for {LOSS_S * 1e3:.0f} ms; the force "
                 f"ramps to zero within {(LOSS_S + RAMP_S) * 1e3:.0f} ms and fades back in "
                 f"over {RECOVER_S:g} s when data returns",
}
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
#: ACK flag: the trainee found a gap in the tissue events (go back).
FLAG_NACK = 1

#: STATE payload, fixed part: sample time [s], tool centre [mm] (3), axis (3),
#: force sent to the instructor's device [N] (3), speed [rpm], normal force
#: magnitude [N], immersed volume [mm^3], the log's epoch, buttons, drill,
#: direction, burr, tissue-event record version, log length, first event's
#: log index, events here.
STATE = struct.Struct("<d3d3d3ddddiIBbBBQQH")
#: One tissue event on the wire: :data:`bonesim.engine.events.TISSUE_FIELDS`,
#: packed, little-endian (83 bytes), of record version
#: :data:`bonesim.engine.events.TISSUE_EVENT_VERSION`.
RECORD = np.dtype([(name, np.dtype(dt).newbyteorder("<"), shape)
                   for name, (dt, shape) in events.TISSUE_FIELDS.items()])
#: Tissue events that fit in one STATE packet.
MAX_EVENTS = (net.MAX_PAYLOAD - STATE.size) // RECORD.itemsize
#: STATE packets a trainee behind the log gets per sample (catching up on a
#: late join's snapshot at up to ``MAX_BURST * MAX_EVENTS`` events per ms).
MAX_BURST = 4
#: ACK payload: log events held (u64), the log's epoch (i32).
ACK = struct.Struct("<Qi")


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
    epoch : int
        The epoch of the tissue-event log the sample came with (the last
        ``RESET`` of the instructor's tissue stream).
    buttons, drill, direction, burr : int
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
               direction, burr, log_len, first, records) -> int:
    """Write a STATE payload into ``buf``; returns its length [bytes].

    Parameters
    ----------
    buf : bytearray
        At least :data:`bonesim.net.packets.MAX_PAYLOAD` bytes.
    t_s : float
        Sample time [s].
    pos, axis, force : (3,) float
        Tool centre [mm], drill axis, force on the instructor's device [N].
    speed, mag, volume : float
        Drill speed [rpm], normal force magnitude [N], immersed volume [mm^3].
    epoch, buttons, drill, direction, burr : int
        The log's epoch and the sample's buttons, drill, direction and burr.
    log_len, first : int
        The log's length and the log index of ``records[0]``.
    records : ndarray of :data:`RECORD`
        At most :data:`MAX_EVENTS` tissue events.
    """
    k = len(records)
    STATE.pack_into(buf, 0, t_s, pos[0], pos[1], pos[2], axis[0], axis[1], axis[2],
                    force[0], force[1], force[2], speed, mag, volume, epoch, buttons,
                    drill, direction, burr, events.TISSUE_EVENT_VERSION, log_len, first, k)
    end = STATE.size + k * RECORD.itemsize
    if k:
        buf[STATE.size:end] = net.pack_records(records)
    return end


def check_tissue_version(version, packet: str) -> None:
    """Refuse a tissue-event record version this side does not know.

    Parameters
    ----------
    version : int or None
        The version a packet announces (None: it announces none).
    packet : str
        The packet, for the message (``"STATE"``, ``"WELCOME"``).

    Raises
    ------
    bonesim.net.packets.PacketError
        ``version``, naming the packet and both versions.
    """
    if version != events.TISSUE_EVENT_VERSION:
        said = "no version" if version is None else f"version {version}"
        raise net.PacketError(
            "version", f"the instructor's {packet} packet carries tissue-event records of "
                       f"{said}; this trainee reads version {events.TISSUE_EVENT_VERSION} "
                       "(run the same bonesim release on both machines)")


def unpack_state(payload, st: InstructorState):
    """Read a STATE payload into ``st``.

    Returns
    -------
    log_len, first : int
    records : ndarray of :data:`RECORD`
        The tissue events carried (a read-only view of ``payload``).

    Raises
    ------
    bonesim.net.packets.PacketError
        ``version`` if the records are of another version
        (:func:`check_tissue_version`), ``length`` if the payload size
        disagrees with its event count or carries a non-finite number.
    """
    if len(payload) < STATE.size:
        raise net.PacketError("length", f"STATE payload of {len(payload)} bytes, the fixed "
                                        f"part alone is {STATE.size}")
    (t, px, py, pz, ax, ay, az, fx, fy, fz, speed, mag, vol, epoch, buttons, drill,
     direction, burr, version, log_len, first, k) = STATE.unpack_from(payload, 0)
    check_tissue_version(version, "STATE")
    if len(payload) != STATE.size + k * RECORD.itemsize:
        raise net.PacketError("length", f"STATE says {k} tissue events, the payload holds "
                                        f"{(len(payload) - STATE.size) / RECORD.itemsize:g}")
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
    records = net.unpack_records(memoryview(payload)[STATE.size:], RECORD, "STATE")
    return log_len, first, records


class TissueLog:
    """The current epoch's tissue events, from its ``RESET`` on, indexed from
    0, growing (server side).

    Attributes
    ----------
    rec : ndarray of :data:`RECORD`
        Storage; ``rec[:n]`` is the log.
    n : int
        Events logged.
    """

    def __init__(self, capacity: int = 1 << 14):
        self.rec = np.zeros(capacity, RECORD)
        self.n = 0

    @property
    def epoch(self) -> int:
        """The epoch the log's leading ``RESET`` names (-1 while empty)."""
        return int(self.rec["n"][0]) if self.n else -1

    def clear(self) -> None:
        self.n = 0

    def extend(self, ev: dict) -> None:
        """Append tissue events given column-wise
        (:data:`bonesim.engine.events.TISSUE_FIELDS`)."""
        k = len(ev["kind"])
        if self.n + k > len(self.rec):
            cap = len(self.rec)
            while cap < self.n + k:
                cap *= 2
            grown = np.zeros(cap, RECORD)
            grown[:self.n] = self.rec[:self.n]
            self.rec = grown
        for f in events.TISSUE_FIELDS:
            self.rec[f][self.n:self.n + k] = ev[f]
        self.n += k

    def columns(self, start: int = 0, stop: int | None = None) -> dict:
        """Events ``start .. stop-1`` column-wise (copies)."""
        part = self.rec[start:self.n if stop is None else stop]
        return {f: part[f].copy() for f in events.TISSUE_FIELDS}


def _voxels(bricks, b, o) -> np.ndarray:
    """Voxel indices (n, 3) int32 of brick rows ``b`` and in-brick offsets ``o``."""
    out = np.empty((len(b), 3), np.int32)
    out[:, 0] = bricks[b, 0] * 8 + (o >> 6)
    out[:, 1] = bricks[b, 1] * 8 + ((o >> 3) & 7)
    out[:, 2] = bricks[b, 2] * 8 + (o & 7)
    return out


def tissue_snapshot(initial_density, label, bricks, density, body, pose, alive,
                    epoch: int = 0, t_s: float = 0.0) -> dict:
    """The tissue events that turn the initial tissue into a live one.

    A ``RESET`` (``n`` = ``epoch``), then per body other than 0 one ``SPLIT``
    block of its voxels that held material initially (split from body 0,
    which holds every voxel after a reset), a ``POSE`` for every body so
    created and for body 0 when it is not at the identity, and a ``REMOVED``
    record for every voxel present initially and gone now. A
    :class:`~bonesim.engine.replica.TissueReplica` that applies them holds the live
    tissue's occupancy, body ids and poses. A body left with no voxel that
    ever held material cannot be split off and is not created.

    Parameters
    ----------
    initial_density, density : (n_bricks, 512) float32
        The case's initial and the live tissue density.
    label : (n_bricks, 512) uint8
        Structure label per voxel (the removals' labels).
    bricks : (n_bricks, 3) int
        Brick coordinates [bricks].
    body : (n_bricks, 512) uint8
        Live body id per voxel.
    pose : (max_bodies, 7) float64
        Live body poses ``(tx, ty, tz [mm], qw, qx, qy, qz)``.
    alive : (max_bodies,) uint8
        Live bodies.
    epoch : int
        The epoch the ``RESET`` names.
    t_s : float
        The events' time [s].

    Returns
    -------
    dict of str -> ndarray
        Tissue-event columns (:data:`bonesim.engine.events.TISSUE_FIELDS`).
    """
    held = np.asarray(initial_density) > 0
    parts = [events.empty_events(1)]
    parts[0]["kind"][0] = events.RESET
    parts[0]["n"][0] = epoch
    made = [0]
    bod = np.asarray(body)
    for b in np.unique(bod[held]):
        if b == 0 or not alive[b]:
            continue
        bb, oo = np.nonzero(held & (bod == b))
        ev = events.empty_events(len(bb))
        ev["kind"][:] = events.SPLIT
        ev["body"][:] = b
        ev["ijk"][:] = _voxels(bricks, bb, oo)
        ev["n"][:] = len(bb)
        parts.append(ev)
        made.append(int(b))
    for b in made:
        if b == 0 and tuple(float(v) for v in pose[0]) == IDENTITY_POSE:
            continue
        ev = events.empty_events(1)
        ev["kind"][0] = events.POSE
        ev["body"][0] = b
        ev["value"][0] = pose[b]
        parts.append(ev)
    bb, oo = np.nonzero(held & (np.asarray(density) <= 0))
    ev = events.empty_events(len(bb))
    ev["kind"][:] = events.REMOVED
    ev["body"][:] = bod[bb, oo]
    ev["label"][:] = np.asarray(label)[bb, oo]
    ev["ijk"][:] = _voxels(bricks, bb, oo)
    parts.append(ev)
    out = events.concat(parts)
    out["t_s"][:] = t_s
    return out


def session_info(model, burrs=()) -> dict:
    """What a trainee needs to rebuild the instructor's tissue (WELCOME),
    with the tissue-event record version the server streams.

    The case goes by name only: a WELCOME answers a JOIN before its sender
    has proven the key from its address (a replayed JOIN earns one), so it
    names no local path. A trainee drilling a case that is not bundled names
    its own copy (``bonesim tutor join --case``)."""
    case = model.case
    return {"case": getattr(case, "name", model.name),
            "tissue_version": events.TISSUE_EVENT_VERSION,
            "burrs": [model.burr.name] + [b.name for b in burrs],
            "n_bricks": int(model.grid.n_bricks),
            "spacing_mm": float(model.grid.spacing_mm)}
