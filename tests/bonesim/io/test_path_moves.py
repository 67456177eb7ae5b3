"""The planner's proofs of clearance (bonesim.io.path_moves) and its strokes
along the walls (bonesim.io.mastoid_plan.strokes)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from bonesim.io.mastoid_plan import strokes
from bonesim.io.path_moves import PathBuilder, first_bone, segment_clear, trace_floors
from bonesim.physics.clearance import Clearance


def test_floors_and_segment_checks_against_dense_sampling():
    """The planner's two proofs on a clearance field: every depth above a
    traced floor is clear and the floor is where it stops being so; a move
    found clear is clear at every point, one clear by a margin is found so."""
    rng = np.random.default_rng(5)
    lab = np.zeros((40, 40, 40), np.uint8)
    for _ in range(12):
        lo = rng.integers(0, 36, 3)
        hi = lo + rng.integers(1, 6, 3)
        lab[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = 1
    cl = Clearance(lab, (0.3, 0.4, 0.5), (0, 0, 0), [1])
    clear = 2.0

    def gap(p):
        return cl.distance(p) - clear

    base = np.column_stack([rng.uniform(0, 12, 200), rng.uniform(0, 16, 200),
                            np.full(200, -8.0)])
    view = np.array([0.0, 0.0, 1.0])
    floor = trace_floors(gap, base, view, 0.0, 40.0)
    for b, f in zip(base, floor):
        if not np.isfinite(f):
            assert gap(b)[0] < 0.0                       # starts too close
            continue
        t = np.linspace(0.0, f, 400)
        assert gap(b + t[:, None] * view).min() >= -1e-9
        if f < 40.0:
            assert gap(b + f * view)[0] < 2e-3
    found = 0
    for _ in range(300):
        p, q = rng.uniform(-3, 20, (2, 3))
        dense = gap(p + np.linspace(0, 1, 3000)[:, None] * (q - p)).min()
        ok = segment_clear(gap, p, q, 0.0)
        if ok:
            found += 1
            assert dense >= -1e-9
        elif dense >= 0.05:
            raise AssertionError(f"a move clear by {dense:.3f} mm was refused")
    assert 30 < found < 270


def test_path_builder_samples_state_and_burr():
    path = PathBuilder((0.0, 0.0, 0.0))
    path.go((10.0, 0.0, 0.0), 10.0, drill=True)          # 1 s, burr 0
    path.burr = 1
    path.go((10.0, 5.0, 0.0), 5.0)                        # 1 s, burr 1, drill off
    t, pos, state, burr = path.sampled(10.0)
    assert t[-1] == 2.0 and len(t) == 21
    np.testing.assert_allclose(pos[10], [10.0, 0.0, 0.0])
    assert state[1:11, 0].all() and not state[11:, 0].any()
    assert (burr[1:11] == 0).all() and (burr[11:] == 1).all()
    assert path.drill_s == 1.0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(1.5, 6.0))
def test_strokes_cover_the_region_along_its_edge(seed, step):
    """Every cell of a region lies within a stroke spacing of a stroke; the
    strokes stay in the region, move between neighbouring cells, and the first
    runs along the edge (half a spacing in)."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((40, 36), bool)
    for _ in range(3):
        c = rng.integers(8, 30, 2)
        r = rng.integers(3, 10, 2)
        y, x = np.ogrid[:40, :36]
        mask |= ((y - c[0]) / r[0]) ** 2 + ((x - c[1]) / r[1]) ** 2 <= 1.0
    out = strokes(mask, step)
    assert out
    cells = np.concatenate(out)
    assert mask[cells[:, 0], cells[:, 1]].all()
    for s in out:
        if len(s) > 1:
            assert np.abs(np.diff(s, axis=0)).max() <= 2      # neighbours (rounding)
    hit = np.zeros_like(mask)
    hit[cells[:, 0], cells[:, 1]] = True
    near = ndimage.distance_transform_edt(~hit)
    assert near[mask].max() <= step + 1.5
    edt = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
    first = out[0]
    if edt.max() > step:
        assert np.abs(edt[first[:, 0], first[:, 1]] - 0.5 * step).max() <= 1.5


def _first_bone_ref(is_bone, origin, spacing, base, view, depth):
    """Every ray sampled at every depth, then the first bone sample."""
    shape = np.array(is_bone.shape)
    ray = base[:, None, :] + depth[None, :, None] * view
    idx = np.floor((ray - origin) / spacing + 0.5).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < shape), axis=-1)
    hit = np.zeros(ok.shape, dtype=bool)
    hit[ok] = is_bone[tuple(idx[ok].T)]
    out = np.full(len(base), np.inf)
    out[hit.any(axis=1)] = depth[np.argmax(hit[hit.any(axis=1)], axis=1)]
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), per_axis=st.booleans())
def test_first_bone_is_the_first_bone_sample_of_each_ray(seed, per_axis):
    """Rays into, past and beside a random bone block, from inside and
    outside the volume, with scalar and per-axis spacing: the depths of
    sampling every ray at every depth, to the bit."""
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(3, 14, 3))
    bone = rng.random(shape) < rng.uniform(0.01, 0.4)
    spacing = rng.uniform(0.1, 0.8, 3) if per_axis else float(rng.uniform(0.1, 0.8))
    origin = rng.uniform(-4, 4, 3)
    extent = np.asarray(spacing) * np.array(shape)
    view = rng.normal(size=3)
    view /= np.linalg.norm(view)
    base = origin - 0.3 * extent + rng.random((50, 3)) * 1.6 * extent - 2.0 * view
    depth = np.arange(0.0, 3.0 * extent.max(), float(np.min(spacing)) / 2)
    got = first_bone(bone, origin, spacing, base, view, depth)
    np.testing.assert_array_equal(got, _first_bone_ref(bone, origin, spacing, base, view,
                                                       depth))


def test_first_bone_names_a_volume_that_is_not_3d():
    with pytest.raises(ValueError, match="is_bone must be 3-D"):
        first_bone(np.ones((4, 4), bool), np.zeros(3), 0.5, np.zeros((1, 3)),
                   np.array([1.0, 0.0, 0.0]), np.arange(3.0))
