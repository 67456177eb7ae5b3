"""The step's compiled intake and bookkeeping against the numpy they replace."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine.model import Sample, step
from bonesim.engine.step_io import store_step, unit_pose

from tests.bonesim.fakes import block_model

_any = hs.floats(allow_nan=True, allow_infinity=True, width=64)


def _numpy_pose(pos, ax):
    """The step's former numpy: (ok, unit axis)."""
    ax = ax.copy()
    x, y, z = (float(v) for v in ax)
    norm = math.sqrt(x * x + y * y + z * z)
    if not norm > 0.0 or not math.isfinite(norm) or not np.isfinite(pos).all():
        return False, ax
    ax /= norm
    return True, ax


@settings(max_examples=300, deadline=None)
@given(pos=hs.tuples(_any, _any, _any), ax=hs.tuples(_any, _any, _any))
def test_unit_pose_is_the_numpy_bit_for_bit(pos, ax):
    pos, ax = np.array(pos, np.float64), np.array(ax, np.float64)
    ok_ref, ax_ref = _numpy_pose(pos, ax)
    got = ax.copy()
    assert unit_pose(pos.copy(), got) == ok_ref
    if ok_ref:
        assert got.tobytes() == ax_ref.tobytes()


@settings(max_examples=50, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1))
def test_store_step_is_the_numpy(seed):
    rng = np.random.default_rng(seed)
    rbl, lost = rng.integers(0, 100, 5), rng.integers(0, 100, 5)
    pos, ax, out = rng.normal(size=3), rng.normal(size=3), rng.normal(size=11)
    want = rbl + lost
    pm, am, f = np.zeros(3), np.zeros(3), np.zeros(3)
    store_step(rbl, lost, pm, pos, am, ax, f, out)
    np.testing.assert_array_equal(rbl, want)
    assert pm.tobytes() == pos.tobytes() and am.tobytes() == ax.tobytes()
    assert f.tobytes() == out[:3].tobytes()


@pytest.mark.parametrize("pos,axis", [((1.0, math.nan, 2.0), (0, 0, 1.0)),
                                      ((1.0, 1.0, 2.0), (0, 0, 0.0)),
                                      ((1.0, 1.0, 2.0), (math.inf, 0, 1.0))])
def test_step_refuses_a_bad_pose_in_one_line(pos, axis):
    m, st = block_model()
    with pytest.raises(ValueError, match="position must be finite and axis non-zero"):
        step(m, st, Sample(0.0, np.array(pos), np.array(axis), True, 60000.0, 1))


def test_step_takes_lists_and_float32():
    m, st = block_model()
    a = step(m, st, Sample(0.0, [10.0, 10.0, 9.75], [0, 0, 2], True, 60000.0, 1)).copy()
    m2, st2 = block_model()
    b = step(m2, st2, Sample(0.0, np.array([10.0, 10.0, 9.75], np.float32),
                             np.array([0, 0, 2], np.float32), True, 60000.0, 1))
    assert a.tobytes() == b.tobytes() and np.any(a != 0)
    np.testing.assert_array_equal(st.axis, [0.0, 0.0, 1.0])
