"""A large fragment measured in slices (bonesim.engine.rigid_measure): the
same contact samples as body_samples, the same mass properties to rounding,
and the fragment stays put until measured."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.engine.bodies import split_body
from bonesim.engine.model import make_model, make_state
from bonesim.engine.rigid_measure import MeasureJob, measure_budget, needs_slices
from bonesim.engine.rigid_set import body_samples
from bonesim.io.burrs import load_burr

BONE = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))


def _fragment(seed: int):
    """A slab and, apart from it, a lumpy block of bone made body 1."""
    rng = np.random.default_rng(seed)
    lab = np.zeros((40, 36, 44), np.uint8)
    lab[:, :, :4] = 1
    blk = rng.random((20, 18, 22)) < 0.8
    blk[:, :, 0] = True                       # keep it mostly one piece
    lab[6:26, 8:26, 14:36] = blk
    m = make_model(lab, 0.5, [BONE], load_burr("cutting-1mm"))
    st = make_state(m)
    split_body(st, 0, np.argwhere(lab[:, :, 10:] > 0) + [0, 0, 10])
    return m, st


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("budget", [1, 37, 5000])
def test_sliced_measurement_equals_body_samples(seed, budget):
    m, st = _fragment(seed)
    ref = body_samples(st, 1)
    job = MeasureJob(st, 1)
    slices = 0
    while not job.advance(st, budget, 1024):
        slices += 1
    got = job.result
    assert slices + 1 >= ref["voxels"] // (8 * budget) and got["voxels"] == ref["voxels"]
    np.testing.assert_array_equal(got["smp"], ref["smp"])
    np.testing.assert_array_equal(got["nrm"], ref["nrm"])
    assert got["mass_kg"] == pytest.approx(ref["mass_kg"], rel=1e-12)
    np.testing.assert_allclose(got["com_mm"], ref["com_mm"], rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got["inertia"], ref["inertia"], rtol=1e-7,
                               atol=1e-9 * np.abs(ref["inertia"]).max())


def test_a_large_fragment_stays_put_until_measured_then_wakes():
    m, st = _fragment(0)
    split_body(st, 0, np.argwhere(np.ones((2, 2, 2), bool)))     # a small body 2
    assert needs_slices(st, 1) and not needs_slices(st, 2)
    rs = st.rigid
    with pytest.raises(ValueError, match="being measured"):
        rs.wake_body(st, 1)
    tool = np.array([-50.0, -50.0, -50.0])             # far away: nothing pushed
    steps = 0
    while not rs._measuring[1].done:
        rs.advance(st, steps * 1e-3, tool, True, 0.5, 1.0)
        steps += 1
    assert steps > 1
    s = rs.wake_body(st, 1)                            # measured: wakes now
    assert s >= 0 and rs.owner[s] == 1 and not rs._measuring
    ref = body_samples(st, 1)
    assert rs.mass[s] == pytest.approx(ref["mass_kg"], rel=1e-12)
    assert measure_budget() >= 1


def test_at_once_measures_a_large_fragment_now_as_body_samples_does():
    m, st = _fragment(0)
    rs = st.rigid
    with pytest.raises(ValueError, match="being measured"):
        rs.wake_body(st, 1)                            # a slice job starts ...
    s = rs.wake_body(st, 1, at_once=True)              # ... and is dropped for the one-shot
    ref = body_samples(st, 1)
    assert s >= 0 and rs.owner[s] == 1 and not rs._measuring
    assert rs.mass[s] == ref["mass_kg"] and rs.n_smp[s] == len(ref["smp"])
    np.testing.assert_array_equal(rs.smp[s, :rs.n_smp[s]], ref["smp"])


def test_a_reset_forgets_a_measurement_under_way():
    m, st = _fragment(1)
    with pytest.raises(ValueError):
        st.rigid.wake_body(st, 1)
    st.rigid.clear()
    assert not st.rigid._measuring


def test_a_grab_of_a_fragment_being_measured_happens_when_it_is_measured():
    from bonesim.engine.rigid import GRABBED

    m, st = _fragment(0)
    rs = st.rigid
    tool = np.array([8.0, 8.0, 20.0])
    rs.grab_body(st, 1, tool)
    assert rs.slot_of(1) < 0 and 1 in rs._grab_after
    steps = 0
    while rs.slot_of(1) < 0:
        rs.advance(st, steps * 1e-3, tool, True, 0.5, 1.0)
        steps += 1
        assert steps < 10_000
    assert steps > 1 and rs.mode[rs.slot_of(1)] == GRABBED and not rs._grab_after
