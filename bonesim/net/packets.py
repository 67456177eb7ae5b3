"""Authenticated UDP packets for haptic tutoring and the remote nerve monitor.

Every datagram is one packet::

    header   36 bytes, little-endian (see HEADER)
             magic  b"BSIM"
             version u8     PROTOCOL_VERSION
             kind    u8     what the payload is (see KIND_*)
             flags   u16    kind-specific bits
             nonce   u64    the *receiver's* session nonce, echoed by the sender
             seq     u64    per sender, strictly increasing
             t_s     f64    sender's monotonic clock when sent [s]
             length  u32    payload bytes
    payload  length bytes
    tag      16 bytes: HMAC-SHA256(key, header + payload), truncated

The key is shared by both ends (:func:`load_key`, :func:`write_key`). The tag
stops forged and altered packets; the nonce binds a packet to one session (a
receiver draws a fresh random nonce each time it joins, so packets captured in
an earlier session are rejected); the sequence number stops replays and late
duplicates inside a session; the send time lets the receiver drop packets that
were delayed too long (:class:`Inbox`). Packets are not encrypted: a
simulator's tool poses are not secret, but nobody may steer a trainee's device.

Packets stay below :data:`MAX_DATAGRAM` bytes so that they are never
fragmented on an Ethernet path. :class:`Codec` encodes and decodes;
:class:`Inbox` is the receiving end's acceptance policy with its drop counters.
"""
from __future__ import annotations

import hmac
import json
import math
import socket
import struct
import time
from typing import NamedTuple

from bonesim.errors import BonesimError
from bonesim.net.keys import (DEFAULT_KEY_HELP, KEY_ENV, MIN_KEY_BYTES,  # noqa: F401 (re-exported)
                              load_key, new_nonce, write_key)

__all__ = ["PROTOCOL_VERSION", "MAGIC", "HEADER", "TAG_BYTES", "MAX_DATAGRAM",
           "MAX_PAYLOAD", "MIN_KEY_BYTES", "KEY_ENV", "DEFAULT_KEY_HELP",
           "DEFAULT_PORT", "MONITOR_PORT", "CLOCK_DRIFT", "KIND_JOIN", "KIND_WELCOME",
           "KIND_ACK", "KIND_BYE", "SESSION_KINDS", "REASONS", "PacketError", "Packet",
           "load_key", "write_key", "new_nonce", "Codec", "udp_socket", "COUNTER_OF",
           "COUNTERS", "Inbox", "WELCOME_NONCE", "JOIN_PAD", "datagrams", "Peer", "SessionServer",
           "Welcome", "SessionClient", "pack_records", "unpack_records"]

#: Wire-format version; a packet of any other version is dropped.
PROTOCOL_VERSION = 1
MAGIC = b"BSIM"
#: magic, version, kind, flags, nonce, seq, t_s, payload length.
HEADER = struct.Struct("<4sBBHQQdI")
TAG_BYTES = 16
#: Largest datagram we send or accept [bytes]: below a 1500-byte Ethernet MTU
#: minus IPv4/IPv6 and UDP headers, so no IP fragmentation.
MAX_DATAGRAM = 1400
MAX_PAYLOAD = MAX_DATAGRAM - HEADER.size - TAG_BYTES
#: Default UDP port of ``bonesim tutor serve``.
DEFAULT_PORT = 47810
#: Default UDP port of the nerve monitor's console server (``bonesim monitor``).
MONITOR_PORT = DEFAULT_PORT + 1
#: Clock-rate difference between two machines the staleness check tolerates
#: (crystal oscillators drift by tens of ppm; 500 ppm is generous).
CLOCK_DRIFT = 5e-4

# Session packet kinds shared by every service (tutoring, nerve monitor).
# Services number their own data kinds from 16 upward.
#: receiver -> sender: "send to me"; nonce = the joiner's own fresh nonce.
KIND_JOIN = 1
#: sender -> receiver: join accepted; payload names the sender's nonce.
KIND_WELCOME = 2
#: receiver -> sender: keep-alive / acknowledgement (service-defined payload).
KIND_ACK = 3
#: either way: the session ends.
KIND_BYE = 4
SESSION_KINDS = frozenset((KIND_JOIN, KIND_WELCOME, KIND_ACK, KIND_BYE))

#: Why a datagram could not be decoded (:attr:`PacketError.reason`).
REASONS = ("short", "magic", "version", "length", "auth", "kind")


class PacketError(ValueError):
    """A datagram that is not a valid packet.

    Attributes
    ----------
    reason : str
        One of :data:`REASONS`: ``short`` (fewer bytes than header + tag),
        ``magic`` (not a bonesim packet), ``version`` (another protocol
        version), ``length`` (payload length field disagrees with the
        datagram), ``auth`` (HMAC tag wrong: forged, altered or other key),
        ``kind`` (authentic, but a kind this receiver does not handle).
    """

    def __init__(self, reason: str, message: str):
        if reason not in REASONS:
            raise ValueError(f"unknown packet error reason {reason!r}")
        self.reason = reason
        super().__init__(f"packet rejected ({reason}): {message}")


class Packet(NamedTuple):
    """A decoded, authenticated packet.

    Attributes
    ----------
    kind : int
    nonce : int
        Session nonce the sender echoed (u64).
    seq : int
        Sender's sequence number (u64).
    t_s : float
        Sender's clock when sent [s].
    payload : bytes
    flags : int
    """

    kind: int
    nonce: int
    seq: int
    t_s: float
    payload: bytes
    flags: int = 0


# -------------------------------------------------------------------- codec
class Codec:
    """Encodes and decodes packets under one key.

    Parameters
    ----------
    key : bytes
        Shared key (>= 16 bytes).
    kinds : iterable of int, optional
        Kinds :meth:`decode` accepts (default: any). An authentic packet of
        another kind raises ``PacketError("kind")``.
    seq0 : int, optional
        First sequence number. Default: the wall clock in nanoseconds, so a
        restarted sender keeps counting upward.
    clock : callable
        Sender clock for packets encoded without ``t_s`` [s]
        (default :func:`time.monotonic`).
    """

    def __init__(self, key: bytes, kinds=None, seq0: int | None = None,
                 clock=time.monotonic):
        key = bytes(key)
        if len(key) < MIN_KEY_BYTES:
            raise ValueError(f"key must be at least {MIN_KEY_BYTES} bytes")
        self._mac = hmac.new(key, digestmod="sha256")
        self.kinds = None if kinds is None else frozenset(int(k) for k in kinds)
        self.seq = time.time_ns() if seq0 is None else int(seq0)
        self.clock = clock
        self._buf = bytearray(MAX_DATAGRAM)
        self._view = memoryview(self._buf)

    def _tag(self, data) -> bytes:
        h = self._mac.copy()
        h.update(data)
        return h.digest()[:TAG_BYTES]

    def encode_into(self, kind: int, payload, nonce: int, t_s: float | None = None,
                    flags: int = 0) -> memoryview:
        """Encode into the codec's own buffer (no new bytes object).

        Returns
        -------
        memoryview
            The packet; valid until the next ``encode*`` call (hand it to
            ``socket.sendto`` right away).
        """
        n = len(payload)
        if n > MAX_PAYLOAD:
            raise ValueError(f"payload of {n} bytes exceeds the {MAX_PAYLOAD}-byte limit")
        self.seq += 1
        t = self.clock() if t_s is None else t_s
        HEADER.pack_into(self._buf, 0, MAGIC, PROTOCOL_VERSION, kind, flags, nonce,
                         self.seq, t, n)
        end = HEADER.size + n
        self._buf[HEADER.size:end] = payload
        self._buf[end:end + TAG_BYTES] = self._tag(self._view[:end])
        return self._view[:end + TAG_BYTES]

    def encode(self, kind: int, payload, nonce: int, t_s: float | None = None,
               flags: int = 0) -> bytes:
        """One packet as bytes; assigns the next sequence number.

        Parameters
        ----------
        kind : int
            Packet kind (u8).
        payload : bytes-like
            At most :data:`MAX_PAYLOAD` bytes.
        nonce : int
            The receiver's session nonce (u64).
        t_s : float, optional
            Send time [s]; default the codec's clock now.
        flags : int
            Kind-specific bits (u16).
        """
        return bytes(self.encode_into(kind, payload, nonce, t_s, flags))

    def decode(self, data) -> Packet:
        """Check and unpack one datagram.

        Raises
        ------
        PacketError
            With ``reason`` saying what is wrong (checked in the order short,
            magic, version, length, auth, kind).
        """
        n = len(data)
        if n < HEADER.size + TAG_BYTES:
            raise PacketError("short", f"{n} bytes, a packet has at least "
                                       f"{HEADER.size + TAG_BYTES}")
        magic, version, kind, flags, nonce, seq, t_s, length = HEADER.unpack_from(data, 0)
        if magic != MAGIC:
            raise PacketError("magic", f"starts with {bytes(magic)!r}, not {MAGIC!r}")
        if version != PROTOCOL_VERSION:
            raise PacketError("version", f"protocol version {version}, this end speaks "
                                         f"{PROTOCOL_VERSION}")
        end = HEADER.size + length
        if end + TAG_BYTES != n:
            raise PacketError("length", f"header says {length} payload bytes, the "
                                        f"datagram holds {n - HEADER.size - TAG_BYTES}")
        mv = memoryview(data)
        if not hmac.compare_digest(self._tag(mv[:end]), mv[end:]):
            raise PacketError("auth", "HMAC tag does not match (forged, altered, or "
                                      "another key)")
        if self.kinds is not None and kind not in self.kinds:
            raise PacketError("kind", f"kind {kind} is not handled here")
        return Packet(kind, nonce, seq, t_s, bytes(mv[HEADER.size:end]), flags)


# ------------------------------------------------------------------- socket
def udp_socket(host: str = "0.0.0.0", port: int = 0) -> socket.socket:
    """A bound non-blocking UDP socket with roomy buffers.

    Raises
    ------
    BonesimError
        If the address cannot be bound (in use, not local, no permission).
    """
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, port))
    except OSError as exc:
        s.close()
        raise BonesimError(f"cannot bind UDP {host}:{port}: {exc.strerror}",
                           field="--port") from None
    for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
        try:
            s.setsockopt(socket.SOL_SOCKET, opt, 1 << 20)
        except OSError:
            pass
    s.setblocking(False)
    return s


# -------------------------------------------------------------------- inbox
#: Decode failures -> the :class:`Inbox` counter they are counted under.
COUNTER_OF = {"short": "malformed", "magic": "malformed", "length": "malformed",
               "kind": "malformed", "version": "version", "auth": "auth"}
COUNTERS = ("accepted", "malformed", "version", "auth", "nonce", "duplicate", "stale")


class Inbox:
    """A receiver's acceptance policy for one session.

    A datagram is accepted when it decodes (:meth:`Codec.decode`), carries
    this session's nonce, has a sequence number above the last accepted one
    (older, repeated or reordered packets are dropped as ``duplicate``) and is
    not stale (a ``BYE`` never is: it only ends the session). Staleness works
    without synchronized clocks: the offset between
    the sender's and the receiver's clocks is estimated as the smallest
    ``now - t_s`` seen over accepted packets (the fastest delivery; allowed
    to creep up by :data:`CLOCK_DRIFT` per second so that a slower sender
    clock does not eventually make everything stale), and a packet whose
    ``now - t_s`` exceeds that offset by more than ``stale_s`` is dropped.

    Parameters
    ----------
    codec : Codec
    nonce : int or None
        This session's nonce; None accepts any (a server waiting for JOINs).
    stale_s : float
        Largest extra delay accepted [s].

    Attributes
    ----------
    counters : dict of str -> int
        ``accepted`` and one count per drop reason: ``malformed`` (short,
        bad magic, bad length, unhandled kind), ``version``, ``auth``,
        ``nonce``, ``duplicate`` (seq not above the last accepted: replays,
        repeats, reordering) and ``stale``.
    last_seq : int
        Sequence number of the last accepted packet (-1 before any).
    offset_s : float
        Current clock-offset estimate, receiver minus sender [s] (NaN before
        the first packet).
    last_accept_s : float
        Receiver time of the last accepted packet [s] (NaN before any).
    """

    def __init__(self, codec: Codec, nonce: int | None, stale_s: float):
        if not stale_s > 0:
            raise ValueError("stale_s must be positive")
        self.codec = codec
        self.nonce = nonce
        self.stale_s = float(stale_s)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.last_seq = -1
        self.offset_s = math.nan
        self._offset_at = math.nan
        self.last_accept_s = math.nan
        self.last_error: PacketError | None = None

    def reset(self, nonce: int | None) -> None:
        """Start a new session (new nonce; sequence and clock forgotten)."""
        self.nonce = nonce
        self.last_seq = -1
        self.offset_s = math.nan
        self._offset_at = math.nan
        self.last_accept_s = math.nan

    def age_s(self, t_s: float, now_s: float) -> float:
        """How much later than the fastest delivery a packet sent at ``t_s``
        arrives at ``now_s`` [s] (0 before the first packet)."""
        if self.offset_s != self.offset_s:
            return 0.0
        off = self.offset_s + CLOCK_DRIFT * (now_s - self._offset_at)
        return (now_s - t_s) - off

    def accept(self, data, now_s: float) -> Packet | None:
        """The packet if ``data`` is acceptable, else None (and counted).

        Parameters
        ----------
        data : bytes-like
            One datagram.
        now_s : float
            Receiver's clock [s].
        """
        try:
            p = self.codec.decode(data)
        except PacketError as exc:
            self.counters[COUNTER_OF[exc.reason]] += 1
            self.last_error = exc
            return None
        return self.admit(p, now_s)

    def admit(self, p: Packet, now_s: float) -> Packet | None:
        """The session checks of :meth:`accept` (nonce, sequence, staleness)
        on an already decoded packet; the packet, or None (and counted)."""
        c = self.counters
        if self.nonce is not None and p.nonce != self.nonce:
            c["nonce"] += 1
            return None
        if p.seq <= self.last_seq:
            c["duplicate"] += 1
            return None
        delay = now_s - p.t_s
        if not math.isfinite(delay):
            c["malformed"] += 1
            return None
        off = self.offset_s
        if p.kind == KIND_BYE:               # never stale: it only ends the session, and
            self.last_seq = p.seq            # a receiver may read it late (a peer that
            self.last_accept_s = now_s       # just quit, a busy machine)
            c["accepted"] += 1
            return p
        if off != off:                                   # first packet
            self.offset_s = delay
            self._offset_at = now_s
        else:
            off += CLOCK_DRIFT * (now_s - self._offset_at)
            if delay - off > self.stale_s:
                c["stale"] += 1
                return None
            if delay < off:
                off = delay
            self.offset_s = off
            self._offset_at = now_s
        self.last_seq = p.seq
        self.last_accept_s = now_s
        c["accepted"] += 1
        return p

    @property
    def dropped(self) -> int:
        """Datagrams dropped for any reason."""
        return sum(v for k, v in self.counters.items() if k != "accepted")


# ----------------------------------------------------------------- sessions
#: WELCOME payload head: the server's nonce for this receiver (then JSON).
WELCOME_NONCE = struct.Struct("<Q")
#: A JOIN's payload: zeros up to the largest datagram. A server answers a
#: JOIN only with a WELCOME no larger than it, so a JOIN replayed from a
#: forged address earns nothing bigger than itself (no amplification).
JOIN_PAD = MAX_PAYLOAD


def datagrams(sock, buf: bytearray):
    """Yield ``(data, addr)`` for every datagram waiting on a non-blocking
    socket; ``data`` is a view of ``buf``, valid until the next one."""
    while True:
        try:
            n, addr = sock.recvfrom_into(buf)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:                               # e.g. ICMP unreachable echoes
            return
        yield memoryview(buf)[:n], addr


class Peer:
    """A receiver joined to a :class:`SessionServer`.

    Attributes
    ----------
    addr : tuple
        Its UDP address.
    nonce : int
        Its session nonce (packets to it carry this).
    server_nonce : int
        The nonce the server gave it (its packets must carry this).
    inbox : Inbox
        Checks its packets (counted in the server's ``rx``).
    streaming : bool
        Set by the service at the peer's first ACK.
    last_heard : float
        Server time of its last accepted packet [s].

    Services keep their own per-peer fields on it (``make_peer``).
    """

    def __init__(self, addr, nonce: int, server_nonce: int, inbox: "Inbox", join_seq: int,
                 now: float):
        self.addr = addr
        self.nonce = nonce
        self.server_nonce = server_nonce
        self.inbox = inbox
        self.join_seq = join_seq
        self.streaming = False
        self.last_heard = now


class SessionServer:
    """The sending side of a service's sessions (tutoring, the nerve monitor).

    Handles the handshake every service shares: a receiver's ``JOIN``
    (carrying its fresh nonce, padded to :data:`JOIN_PAD`) earns a ``WELCOME``
    with the server's nonce for it and the JSON description ``info``, never
    larger than the JOIN (a smaller JOIN is dropped and counted,
    ``joins_small``), and naming no local path; everything it sends afterwards must
    carry that nonce and pass an :class:`Inbox` (sequence, staleness); ``BYE``
    ends its session and a peer silent for ``timeout_s`` is forgotten. A
    replayed JOIN earns at most a small WELCOME: a service starts streaming
    only at the peer's first ACK.

    Parameters
    ----------
    sock : socket
        Bound, non-blocking UDP socket (anything with ``sendto`` and
        ``recvfrom_into``).
    key : bytes
    info : dict
        Sent (as JSON) in every WELCOME.
    stale_s : float
        Staleness bound of the peers' inboxes [s].
    timeout_s : float
        Forget a peer silent this long [s].
    counters : dict, optional
        The service's counters; ``joins``, ``welcomes``, ``send_errors`` and
        ``peers_dropped`` are added to it.
    make_peer : callable, optional
        Called with each new :class:`Peer` (to add the service's fields).

    Attributes
    ----------
    peers : dict
        Address -> :class:`Peer`.
    rx : dict
        Received datagrams: ``accepted`` and the drops by reason
        (:data:`COUNTERS`), over all peers.
    """

    def __init__(self, sock, key: bytes, info: dict, *, stale_s: float, timeout_s: float,
                 counters: dict | None = None, make_peer=None):
        self.sock = sock
        self.codec = Codec(key, kinds=(KIND_JOIN, KIND_ACK, KIND_BYE))
        self.info = dict(info)
        self._info_json = json.dumps(self.info).encode()
        if WELCOME_NONCE.size + len(self._info_json) > JOIN_PAD:
            raise ValueError(f"the WELCOME description is {len(self._info_json)} bytes; "
                             f"at most {JOIN_PAD - WELCOME_NONCE.size} fit a JOIN's size")
        self.stale_s = float(stale_s)
        self.timeout_s = float(timeout_s)
        self.counters = {} if counters is None else counters
        for k in ("joins", "welcomes", "send_errors", "peers_dropped", "joins_small"):
            self.counters.setdefault(k, 0)
        self.make_peer = make_peer
        self.peers: dict = {}
        self.rx = dict.fromkeys(COUNTERS, 0)
        self.now = 0.0
        self._rbuf = bytearray(MAX_DATAGRAM + 1)

    def receive(self, now: float) -> list:
        """Read every waiting datagram at server time ``now`` [s]; answer
        JOINs, honour BYEs; returns ``(peer, packet)`` for each accepted ACK."""
        self.now = now
        acks = []
        for data, addr in datagrams(self.sock, self._rbuf):
            try:
                p = self.codec.decode(data)
            except PacketError as exc:
                self.rx[COUNTER_OF[exc.reason]] += 1
                continue
            peer = self.peers.get(addr)
            if p.kind == KIND_JOIN:
                self._join(peer, addr, p, now)
                continue
            if peer is None:
                self.rx["nonce"] += 1                 # no session with that sender
                continue
            if peer.inbox.admit(p, now) is None:     # counted in self.rx
                continue
            peer.last_heard = now
            if p.kind == KIND_BYE:
                del self.peers[addr]
            else:
                acks.append((peer, p))
        return acks

    def _join(self, peer, addr, p, now: float) -> None:
        body_len = WELCOME_NONCE.size + len(self._info_json)
        if len(p.payload) < body_len:                # the WELCOME would be larger
            self.counters["joins_small"] += 1
            return
        if peer is not None and p.seq <= peer.join_seq:
            self.rx["duplicate"] += 1                 # a replayed or repeated JOIN
            return
        if peer is None or peer.nonce != p.nonce:    # a new receiver session
            self.counters["joins"] += 1
            peer = Peer(addr, p.nonce, new_nonce(), Inbox(self.codec, None, self.stale_s),
                        p.seq, now)
            peer.inbox.nonce = peer.server_nonce
            peer.inbox.counters = self.rx             # one tally for all peers
            if self.make_peer is not None:
                self.make_peer(peer)
            self.peers[addr] = peer
        peer.join_seq = p.seq
        self.rx["accepted"] += 1
        body = WELCOME_NONCE.pack(peer.server_nonce) + self._info_json
        self.send(peer, KIND_WELCOME, body)
        self.counters["welcomes"] += 1

    def send(self, peer: Peer, kind: int, payload, flags: int = 0) -> None:
        """Send one packet to a peer, stamped with the time of the last
        :meth:`receive` (a full socket buffer counts as a loss)."""
        try:
            self.sock.sendto(self.codec.encode_into(kind, payload, peer.nonce, t_s=self.now,
                                                    flags=flags), peer.addr)
        except OSError:
            self.counters["send_errors"] += 1

    def expire(self, now: float) -> list:
        """Forget peers silent for ``timeout_s``; returns the peers left."""
        for addr in [a for a, c in self.peers.items() if now - c.last_heard > self.timeout_s]:
            del self.peers[addr]
            self.counters["peers_dropped"] += 1
        return list(self.peers.values())

    def bye(self) -> None:
        """Tell every peer the session ends, and forget them."""
        for c in list(self.peers.values()):
            self.send(c, KIND_BYE, b"")
        self.peers.clear()


class Welcome:
    """A WELCOME that :meth:`SessionClient.receive` accepted.

    Attributes
    ----------
    packet : Packet
    new : bool
        It began a new server session (the service resets what it keeps).
    """

    __slots__ = ("packet", "new")

    def __init__(self, packet: Packet, new: bool):
        self.packet = packet
        self.new = new


class SessionClient:
    """The receiving side of a service's session (a trainee, a console).

    :meth:`receive` sends JOIN every ``join_retry_s`` until welcomed (and
    again after ``rejoin_s`` without data), reads the WELCOME (the server's
    nonce and JSON description) and a BYE, and hands the service its own
    packets; the service sends ACKs through :meth:`send`.

    Parameters
    ----------
    host : str
    port : int
    key : bytes
    kinds : iterable of int
        The service's data kinds.
    stale_s, join_retry_s, rejoin_s : float
        [s]
    sock : socket, optional
        Bound non-blocking UDP socket (default: any local port).
    what : str
        The server's role, for error messages ("instructor", "nerve monitor").
    counters : dict, optional
        The service's counters; ``joins_sent``, ``welcomes`` and ``byes`` are
        added to it.

    Attributes
    ----------
    welcomed : bool
    info : dict
        The server's description (from its WELCOME).
    server_nonce : int
    last_valid_s : float
        Time of the last WELCOME or data the service accepted [s] (the
        service sets it for data).
    """

    def __init__(self, host: str, port: int, key: bytes, kinds, *, stale_s: float,
                 join_retry_s: float, rejoin_s: float, sock=None, what: str = "server",
                 counters: dict | None = None):
        try:
            self.addr = (socket.gethostbyname(host), int(port))
        except OSError as exc:
            raise BonesimError(f"cannot resolve {what} host {host!r}: {exc}",
                               field="HOST") from None
        self.sock = sock if sock is not None else udp_socket("0.0.0.0", 0)
        self.codec = Codec(key, kinds=(KIND_WELCOME, KIND_BYE, *kinds))
        self.nonce = new_nonce()
        self.inbox = Inbox(self.codec, self.nonce, stale_s)
        self.join_retry_s = float(join_retry_s)
        self.rejoin_s = float(rejoin_s)
        self.what = what
        self.welcomed = False
        self.server_nonce = 0
        self.info: dict = {}
        self.last_valid_s = math.nan
        self.now = 0.0
        self.counters = {} if counters is None else counters
        for k in ("joins_sent", "welcomes", "byes"):
            self.counters.setdefault(k, 0)
        self._last_join = -math.inf
        self._rbuf = bytearray(MAX_DATAGRAM + 1)

    def send(self, kind: int, payload, flags: int = 0) -> None:
        """Send to the server (a failure is like a lost packet)."""
        nonce = self.nonce if kind == KIND_JOIN else self.server_nonce
        try:
            self.sock.sendto(self.codec.encode_into(kind, payload, nonce, t_s=self.now,
                                                    flags=flags), self.addr)
        except OSError:
            pass

    def receive(self, now: float) -> list:
        """Join if needed, then read every waiting datagram at time ``now``
        [s]. Returns what the service must handle, in order: its data
        packets and a :class:`Welcome` for each WELCOME."""
        self.now = now
        if not self.welcomed or now - self.last_valid_s > self.rejoin_s:
            if now - self._last_join >= self.join_retry_s:
                self.send(KIND_JOIN, bytes(JOIN_PAD))
                self._last_join = now
                self.counters["joins_sent"] += 1
        out = []
        for data, _ in datagrams(self.sock, self._rbuf):
            p = self.inbox.accept(data, now)
            if p is None:
                continue
            if p.kind == KIND_WELCOME:
                try:
                    (server_nonce,) = WELCOME_NONCE.unpack_from(p.payload, 0)
                    info = json.loads(bytes(p.payload[WELCOME_NONCE.size:]))
                    if not isinstance(info, dict):
                        raise ValueError
                except (struct.error, ValueError):
                    self.reject()
                    continue
                new = server_nonce != self.server_nonce
                if new:
                    self.server_nonce = server_nonce
                    self.info = info
                self.welcomed = True
                self.last_valid_s = now
                self.counters["welcomes"] += 1
                out.append(Welcome(p, new))
            elif p.kind == KIND_BYE:
                self.counters["byes"] += 1
                self.welcomed = False
                self.last_valid_s = -math.inf         # link lost now
            else:
                out.append(p)
        return out

    def reject(self) -> None:
        """Count the last accepted packet as malformed after all (the service
        found its payload broken)."""
        self.inbox.counters["malformed"] += 1
        self.inbox.counters["accepted"] -= 1

    def close(self) -> None:
        """Say BYE (if in a session) and close the socket."""
        if self.welcomed:
            self.send(KIND_BYE, b"")
        self.sock.close()


# ------------------------------------------------------------ record payloads
def pack_records(records: np.ndarray) -> bytes:
    """Records of a numpy structured (or plain) array as payload bytes
    (little-endian dtypes travel as they are)."""
    import numpy as np

    return np.ascontiguousarray(records).tobytes()


def unpack_records(payload, dtype, what: str = "payload") -> np.ndarray:
    """The records in ``payload`` (a read-only view; copy to keep changing it).

    Raises
    ------
    PacketError
        ``length`` if the payload is not a whole number of records.
    """
    import numpy as np

    dt = np.dtype(dtype)
    if len(payload) % dt.itemsize:
        raise PacketError("length", f"{what}: {len(payload)} bytes is not a whole number "
                                    f"of {dt.itemsize}-byte records")
    return np.frombuffer(payload, dtype=dt)
