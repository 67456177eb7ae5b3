"""The shared brick hash table and sphere walk against obviously correct
references: a Python dict for the table, brute force for the sphere."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.engine.brick_hash import (BRICK, EMPTY_KEY, brick_voxel_span, find_brick,
                                       pack_brick_key, sphere_voxel_range, table_insert,
                                       table_remove)

_COORD = st.integers(-40, 40)


@settings(max_examples=60, deadline=None)
@given(ops=st.lists(st.tuples(st.booleans(), _COORD, _COORD, _COORD), min_size=1,
                    max_size=120),
       log_cap=st.integers(3, 8))
def test_table_matches_a_dict(ops, log_cap):
    cap = 1 << log_cap
    keys = np.full(cap, EMPTY_KEY, dtype=np.int64)
    vals = np.full(cap, -1, dtype=np.int32)
    ref = {}
    for n, (insert, bi, bj, bk) in enumerate(ops):
        key = int(pack_brick_key(bi, bj, bk))
        if insert and (bi, bj, bk) not in ref and len(ref) < cap - 1:
            table_insert(keys, vals, key, n)
            ref[(bi, bj, bk)] = n
        elif not insert and (bi, bj, bk) in ref:
            table_remove(keys, vals, key)
            del ref[(bi, bj, bk)]
        # every brick in the dict is found, every other probe misses
        for (a, b, c), v in ref.items():
            assert find_brick(keys, vals, a, b, c) == v
        assert find_brick(keys, vals, bi, bj, bk) == ref.get((bi, bj, bk), -1)
        assert int((keys != EMPTY_KEY).sum()) == len(ref)


def test_packed_keys_are_distinct_and_non_negative():
    coords = [(a, b, c) for a in (-3, 0, 5) for b in (-(1 << 19), 0, 1 << 19)
              for c in (-1, 0, 1)]
    packed = {int(pack_brick_key(*c)) for c in coords}
    assert len(packed) == len(coords) and min(packed) >= 0


@settings(max_examples=200, deadline=None)
@given(c=st.floats(-20.0, 20.0), r=st.floats(0.0, 6.0), o=st.floats(-3.0, 3.0),
       h=st.sampled_from([0.25, 0.3, 0.5, 1.0]))
def test_sphere_range_holds_every_voxel_within_reach(c, r, o, h):
    lo, hi = sphere_voxel_range(c, r, o, h)
    # brute force: every voxel whose centre is within r along the axis
    first = math.floor((c - r - o) / h) - 5
    inside = [i for i in range(first, first + int(2 * r / h) + 12)
              if abs(o + h * i - c) <= r]
    assert all(lo <= i < hi for i in inside)
    assert hi - lo <= len(inside) + 4        # at most the slack on each side


@settings(deadline=None)
@given(lo=st.integers(-30, 30), n=st.integers(0, 30), bc=st.integers(-5, 5))
def test_brick_span_is_the_range_inside_the_brick(lo, n, bc):
    hi = lo + n
    x0, x1 = brick_voxel_span(lo, hi, bc)
    want = [x for x in range(BRICK) if lo <= bc * BRICK + x < hi]
    assert list(range(x0, x1)) == want
