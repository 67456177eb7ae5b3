"""The packet codec and the receiver's acceptance policy: round trips, every
rejection reason, forged / replayed / reordered / foreign-session packets, key
files, and a fuzz test that decoding only ever raises PacketError."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.net import packets as net
from bonesim.errors import BonesimError

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
NONCE = 0x1234_5678_9ABC_DEF0


def test_round_trip_and_sequence():
    c = net.Codec(KEY, seq0=100)
    a = c.encode(16, b"hello", NONCE, t_s=12.5, flags=3)
    b = c.encode(16, b"", NONCE, t_s=12.6)
    assert len(a) == net.HEADER.size + 5 + net.TAG_BYTES
    pa, pb = net.Codec(KEY).decode(a), net.Codec(KEY).decode(b)
    assert pa == net.Packet(16, NONCE, 101, 12.5, b"hello", 3)
    assert pb.seq == 102 and pb.payload == b"" and pb.t_s == 12.6
    # encode_into reuses one buffer and gives the same bytes
    c2 = net.Codec(KEY, seq0=100)
    assert bytes(c2.encode_into(16, b"hello", NONCE, t_s=12.5, flags=3)) == a


def test_default_seq_grows_across_codecs_and_clock_is_used():
    first = net.Codec(KEY).encode(16, b"", 1)
    second = net.Codec(KEY, clock=lambda: 7.0).encode(16, b"", 1)
    d = net.Codec(KEY)
    assert d.decode(second).seq > d.decode(first).seq
    assert d.decode(second).t_s == 7.0


def test_payload_limit():
    c = net.Codec(KEY)
    c.encode(16, b"x" * net.MAX_PAYLOAD, NONCE)
    with pytest.raises(ValueError, match="exceeds"):
        c.encode(16, b"x" * (net.MAX_PAYLOAD + 1), NONCE)
    assert len(c.encode(16, b"x" * net.MAX_PAYLOAD, NONCE)) == net.MAX_DATAGRAM


def _reason(data, codec=None):
    with pytest.raises(net.PacketError) as ei:
        (codec or net.Codec(KEY)).decode(data)
    return ei.value.reason


def test_every_reason():
    c = net.Codec(KEY)
    good = c.encode(16, b"payload", NONCE)
    assert _reason(good[:10]) == "short"
    assert _reason(b"XSIM" + good[4:]) == "magic"
    # a different version, correctly signed, is still refused as a version
    bad_v = bytearray(good)
    bad_v[4] = net.PROTOCOL_VERSION + 1
    assert _reason(bytes(bad_v)) == "version"
    assert _reason(good[:-1]) == "length"              # truncated tag
    assert _reason(good + b"\0") == "length"           # trailing garbage
    long_len = bytearray(good)
    struct.pack_into("<I", long_len, 32, 1 << 30)
    assert _reason(bytes(long_len)) == "length"
    assert _reason(good, net.Codec(OTHER_KEY)) == "auth"
    assert _reason(good, net.Codec(KEY, kinds=[17])) == "kind"
    assert net.Codec(KEY, kinds=[16]).decode(good).payload == b"payload"
    with pytest.raises(ValueError):
        net.PacketError("nonsense", "x")
    assert set(net.REASONS) == {"short", "magic", "version", "length", "auth", "kind"}


def test_forged_and_altered_packets_fail_authentication():
    c = net.Codec(KEY)
    good = c.encode(16, b"\x01\x02\x03\x04", NONCE, t_s=1.0)
    forged = net.Codec(OTHER_KEY).encode(16, b"\x01\x02\x03\x04", NONCE, t_s=1.0)
    assert _reason(forged) == "auth"
    for i in range(len(good)):
        if 4 <= i < 5 or 32 <= i < 36 or i < 4:       # version / length / magic
            continue
        flipped = bytearray(good)
        flipped[i] ^= 0x40
        assert _reason(bytes(flipped)) == "auth", f"bit flip at byte {i} accepted"


def test_short_key_is_refused():
    with pytest.raises(ValueError):
        net.Codec(b"short")


# ------------------------------------------------------------------- inbox
def _inbox(stale_s=0.05):
    return net.Inbox(net.Codec(KEY), NONCE, stale_s)


def test_inbox_accepts_in_order_and_counts_drops():
    tx = net.Codec(KEY)
    box = _inbox()
    pkts = [tx.encode(16, bytes([i]), NONCE, t_s=10.0 + i * 1e-3) for i in range(5)]
    for i, p in enumerate(pkts):
        got = box.accept(p, now_s=20.0 + i * 1e-3)
        assert got is not None and got.payload == bytes([i])
    assert box.counters["accepted"] == 5 and box.dropped == 0
    # replayed: every old packet again
    for p in pkts:
        assert box.accept(p, now_s=20.01) is None
    assert box.counters["duplicate"] == 5
    # wrong nonce (a packet of another session), correctly signed
    assert box.accept(tx.encode(16, b"x", NONCE + 1, t_s=10.006), now_s=20.006) is None
    assert box.counters["nonce"] == 1
    # forged, malformed, foreign version
    assert box.accept(net.Codec(OTHER_KEY).encode(16, b"x", NONCE, t_s=10.007),
                      20.007) is None
    assert box.accept(b"garbage", 20.007) is None
    v = bytearray(tx.encode(16, b"x", NONCE, t_s=10.007))
    v[4] = 9
    assert box.accept(bytes(v), 20.007) is None
    assert (box.counters["auth"], box.counters["malformed"], box.counters["version"]) \
        == (1, 1, 1)
    assert box.counters["accepted"] == 5 and box.last_seq == net.Codec(KEY).decode(
        pkts[-1]).seq


def test_inbox_reordered_packets_are_dropped_as_duplicates():
    tx = net.Codec(KEY)
    a = tx.encode(16, b"a", NONCE, t_s=1.000)
    b = tx.encode(16, b"b", NONCE, t_s=1.001)
    box = _inbox()
    assert box.accept(b, 5.002).payload == b"b"
    assert box.accept(a, 5.003) is None
    assert box.counters["duplicate"] == 1


def test_inbox_staleness_uses_the_estimated_clock_offset():
    tx = net.Codec(KEY)
    box = _inbox(stale_s=0.05)
    # sender clock is 1000 s behind the receiver's; 1 ms transit
    assert box.accept(tx.encode(16, b"", NONCE, t_s=1.0), 1001.001) is not None
    assert box.offset_s == pytest.approx(1000.001)
    # 40 ms extra delay: accepted; 80 ms: stale
    assert box.accept(tx.encode(16, b"", NONCE, t_s=1.010), 1001.051) is not None
    assert box.accept(tx.encode(16, b"", NONCE, t_s=1.020), 1001.101) is None
    assert box.counters["stale"] == 1
    # a faster delivery lowers the offset estimate
    assert box.accept(tx.encode(16, b"", NONCE, t_s=1.030), 1001.0305) is not None
    assert box.offset_s == pytest.approx(1000.0005, abs=1e-6)
    assert box.age_s(1.040, 1001.0405) == pytest.approx(0.0, abs=1e-5)   # drift allowance
    # a BYE read 5 s late still ends the session (once: a replay is a duplicate)
    bye = tx.encode(net.KIND_BYE, b"", NONCE, t_s=1.05)
    assert box.accept(bye, 1006.05) is not None and box.counters["stale"] == 1
    assert box.accept(bye, 1006.06) is None and box.counters["duplicate"] == 1


def test_inbox_tolerates_slow_clock_drift():
    """A sender clock 100 ppm slow for an hour must never look stale."""
    tx = net.Codec(KEY)
    box = _inbox(stale_s=0.02)
    for k in range(3601):
        t_recv = float(k)
        t_send = t_recv * (1 - 1e-4)
        assert box.accept(tx.encode(16, b"", NONCE, t_s=t_send), t_recv + 0.001) \
            is not None, f"stale after {k} s"


def test_inbox_reset_starts_a_new_session():
    tx = net.Codec(KEY)
    box = _inbox()
    old = tx.encode(16, b"", NONCE, t_s=1.0)
    assert box.accept(old, 2.0) is not None
    box.reset(NONCE + 7)
    assert box.accept(old, 2.1) is None and box.counters["nonce"] == 1
    assert box.accept(tx.encode(16, b"", NONCE + 7, t_s=1.2), 2.2) is not None
    any_box = net.Inbox(net.Codec(KEY), None, 0.05)
    assert any_box.accept(tx.encode(16, b"", 99, t_s=1.3), 2.3).nonce == 99


# -------------------------------------------------------------------- keys
def test_key_files(tmp_path, monkeypatch):
    p = net.write_key(tmp_path / "k")
    assert (p.stat().st_mode & 0o777) == 0o600
    key = net.load_key(p)
    assert len(key) == 32 and key == bytes.fromhex(p.read_text())
    with pytest.raises(BonesimError, match="exists"):
        net.write_key(p)
    raw = tmp_path / "raw.bin"
    raw_key = bytes(range(7, 247, 7))                  # 35 distinct raw bytes
    raw.write_bytes(raw_key)
    assert net.load_key(raw) == raw_key
    short = tmp_path / "short"
    short.write_text("abcd\n")
    with pytest.raises(BonesimError, match=r"short.*2 bytes"):
        net.load_key(short)
    with pytest.raises(BonesimError, match="not found"):
        net.load_key(tmp_path / "missing")
    monkeypatch.setenv(net.KEY_ENV, raw_key.hex())
    assert net.load_key() == raw_key
    monkeypatch.delenv(net.KEY_ENV)
    with pytest.raises(BonesimError, match=net.KEY_ENV):
        net.load_key()


def test_record_payloads():
    dt = np.dtype([("t", "<f8"), ("v", "<f4", (3,))])
    rec = np.zeros(4, dt)
    rec["t"] = np.arange(4)
    rec["v"] = np.arange(12).reshape(4, 3)
    back = net.unpack_records(net.pack_records(rec), dt)
    np.testing.assert_array_equal(back, rec)
    with pytest.raises(net.PacketError) as ei:
        net.unpack_records(b"\0" * 7, dt, "trace")
    assert ei.value.reason == "length" and "trace" in str(ei.value)


# -------------------------------------------------------------------- fuzz
@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=1600))
def test_fuzz_random_bytes_only_raise_packet_error(data):
    c = net.Codec(KEY, kinds=[16])
    try:
        c.decode(data)
    except net.PacketError as exc:
        assert exc.reason in net.REASONS
    box = net.Inbox(net.Codec(KEY), NONCE, 0.05)
    assert box.accept(data, 1.0) is None


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=200), st.data())
def test_fuzz_bit_flips_never_pass(payload, data):
    c = net.Codec(KEY)
    good = bytearray(c.encode(16, payload, NONCE, t_s=3.0))
    n_flips = data.draw(st.integers(1, 8))
    for _ in range(n_flips):
        bit = data.draw(st.integers(0, len(good) * 8 - 1))
        good[bit // 8] ^= 1 << (bit % 8)
    cut = data.draw(st.integers(0, len(good)))
    pkt = bytes(good[:cut]) if data.draw(st.booleans()) else bytes(good)
    try:
        p = net.Codec(KEY).decode(pkt)
    except net.PacketError as exc:
        assert exc.reason in net.REASONS
    else:                      # flips that cancel out restore the original exactly
        assert p.payload == payload and p.t_s == 3.0


# Issue 24: 'passwordpassword' and 16 zero bytes ran without a warning.
@pytest.mark.parametrize("weak", [b"passwordpassword", bytes(16), b"\xff" * 20,
                                  ("00" * 16).encode(), b"xyz" * 8,
                                  b"Tr0ub4dor&3xyzab"])
def test_keys_under_128_bits_of_entropy_are_refused_in_one_line(tmp_path, monkeypatch, weak):
    p = tmp_path / "weak.key"
    p.write_bytes(weak)
    with pytest.raises(BonesimError, match=r"weak.key: key is too weak: about \d+ bits") \
            as err:
        net.load_key(p)
    assert "\n" not in str(err.value) and "keygen" in str(err.value)
    if b"\0" in weak:
        return                                  # an environment variable holds no NUL
    monkeypatch.setenv(net.KEY_ENV, weak.decode("latin-1"))
    with pytest.raises(BonesimError, match=net.KEY_ENV):
        net.load_key()


def test_key_entropy_estimate():
    from bonesim.net.keys import key_entropy_bits

    assert key_entropy_bits(b"passwordpassword") == pytest.approx(8 * np.log2(26))
    assert key_entropy_bits(bytes(16)) <= 8
    assert key_entropy_bits(bytes(range(16))) == 128          # 16 distinct bytes
    assert key_entropy_bits(bytes(range(0, 256, 8))) == 256   # 32
    assert key_entropy_bits(b"") == 0
    rng = np.random.default_rng(24)
    assert all(key_entropy_bits(rng.bytes(32)) == 256 for _ in range(200))
