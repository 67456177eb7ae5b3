"""The shared brick hash table and sphere walk against obviously correct
references: a Python dict for the table, brute force for the sphere."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.engine.brick_hash import (BRICK, EMPTY_KEY, brick_voxel_span, find_brick,
                                       pack_brick_key, sphere_cells, sphere_cells_bound,
                                       sphere_voxel_range, table_insert, table_remove)

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


@settings(max_examples=60, deadline=None)
@given(c=st.tuples(*[st.floats(-6.0, 6.0)] * 3), r=st.floats(0.0, 4.0),
       h=st.sampled_from([0.25, 0.5, 0.7]), inclusive=st.booleans(),
       seed=st.integers(0, 2**31 - 1))
def test_sphere_cells_lists_exactly_the_voxels_within_reach(c, r, h, inclusive, seed):
    rng = np.random.default_rng(seed)
    o = np.array([-0.3, 0.1, 0.2])
    # bricks around the sphere; some missing, some present but unoccupied
    coords = [(bi, bj, bk) for bi in range(-3, 3) for bj in range(-3, 3) for bk in range(-3, 3)]
    keep = [q for q in coords if rng.random() < 0.7]
    keys = np.full(1024, EMPTY_KEY, dtype=np.int64)
    vals = np.full(1024, -1, dtype=np.int32)
    for n, (bi, bj, bk) in enumerate(keep):
        table_insert(keys, vals, pack_brick_key(bi, bj, bk), n)
    occupied = (rng.random(len(keep)) < 0.8).astype(np.int64)
    out = np.zeros((sphere_cells_bound(r, h), 5), np.int64)
    n = sphere_cells(keys, vals, occupied, c[0], c[1], c[2], r, o[0], o[1], o[2], h,
                     inclusive, out)
    # brute force: every voxel of every occupied brick, in brick then voxel order
    want = []
    for b, (bi, bj, bk) in sorted(enumerate(keep), key=lambda t: t[1]):
        if not occupied[b]:
            continue
        for x in range(BRICK):
            for y in range(BRICK):
                for z in range(BRICK):
                    ijk = (bi * BRICK + x, bj * BRICK + y, bk * BRICK + z)
                    d = [(o[a] + h * ijk[a]) - c[a] for a in range(3)]
                    d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                    if d2 < r * r or (inclusive and d2 == r * r):
                        want.append((b, (x << 6) | (y << 3) | z, *ijk))
    assert [tuple(row) for row in out[:n].tolist()] == want
