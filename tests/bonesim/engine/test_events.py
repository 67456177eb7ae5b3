"""Event rings: consumers drain at their own pace and overflow is detected."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine.events import Cursor, Ring, RingOverflow, tissue_ring


def _push(ring, n, start=0):
    for q in range(start, start + n):
        h = ring.head[0] & (ring.capacity - 1)
        ring.fields["ijk"][h] = (q, q + 1, q + 2)
        ring.fields["label"][h] = q % 7
        ring.fields["t_s"][h] = q * 1e-3
        ring.head[0] += 1


def test_two_consumers_read_everything_once():
    ring = tissue_ring(16)
    a, b = Cursor(ring), Cursor(ring)
    _push(ring, 5)
    got_a = a.drain()
    _push(ring, 7, start=5)
    got_a2 = a.drain()
    got_b = b.drain()
    assert list(got_a["ijk"][:, 0]) == [0, 1, 2, 3, 4]
    assert list(got_a2["ijk"][:, 0]) == list(range(5, 12))
    assert list(got_b["ijk"][:, 0]) == list(range(12))
    assert len(a.drain()["t_s"]) == 0


def test_wrap_around_keeps_order():
    ring = tissue_ring(8)
    c = Cursor(ring)
    for chunk in range(5):
        _push(ring, 6, start=6 * chunk)
        got = c.drain()
        np.testing.assert_array_equal(got["ijk"][:, 0], np.arange(6 * chunk, 6 * chunk + 6))
        np.testing.assert_allclose(got["t_s"], got["ijk"][:, 0] * 1e-3)


def test_overflow_is_reported_not_garbage():
    ring = tissue_ring(8)
    c = Cursor(ring)
    _push(ring, 9)
    with pytest.raises(RingOverflow, match="behind"):
        c.drain()


def test_capacity_must_be_power_of_two():
    with pytest.raises(ValueError, match="power of two"):
        Ring.create(12, x=(np.int32, ()))


def test_append_writes_records_across_the_wrap():
    r = Ring.create(8, t_s=(np.float64, ()), v=(np.float32, (2,)))
    r.append(t_s=[], v=np.zeros((0, 2)))                 # nothing: head stays
    assert r.count == 0
    for a in range(0, 12, 3):                             # 12 records through 8 slots
        r.append(t_s=np.arange(a, a + 3), v=np.arange(2 * a, 2 * a + 6).reshape(3, 2))
    assert r.count == 12
    out = r.read(4, 12)
    np.testing.assert_array_equal(out["t_s"], np.arange(4, 12))
    np.testing.assert_array_equal(out["v"], np.arange(8, 24).reshape(8, 2))
