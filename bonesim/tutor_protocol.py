"""Haptic tutoring's constants and wire format: the instructor state on the wire,
the removal log, the session description.

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
import struct

import numpy as np

from . import net

__all__ = ["KP_N_PER_MM", "LOSS_S", "RAMP_S", "RECOVER_S", "SERVO_HZ", "DEFAULT_PORT",
           "STALE_S", "JOIN_RETRY_S", "KEEPALIVE_S", "NACK_HOLD_S", "REJOIN_S",
           "CLIENT_TIMEOUT_S", "KIND_STATE", "FLAG_NACK", "STATE", "REMOVAL_BYTES",
           "MAX_REMOVALS", "ACK", "RESET_IJK", "InstructorState", "pack_state",
           "unpack_state", "RemovalLog", "removed_voxels", "session_info"]

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
