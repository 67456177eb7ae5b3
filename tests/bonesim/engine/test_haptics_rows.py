"""The row-walking haptic pass (oversampling >= 3) against the per-sample
numpy reference and analytic truths.

The row pass puts the samples of a lattice row into voxels by walking the
row through the grid (:mod:`bonesim.engine.haptics_rows`), not one truncation per
sample; it sums in another order. Two kinds of tolerance follow:

* summation order: the sums agree with the reference to ~1e-13 relative (a
  few thousand terms of float64), so forces and volumes are compared at
  1e-9 relative, densities (float32) at 2e-7 absolute, as for the 2x kernel;
* a sample within floating-point distance of a voxel boundary may land in
  the other voxel. The row pass steps ``h`` along a row from its first
  sample, the reference places each sample at its float32-rounded offset:
  they differ by up to ~4e-7 mm (float32 rounding of <= 4 mm), i.e. < 1e-6
  voxel, plus float64 rounding of the position; the tests
  call a sample *ambiguous* when its voxel coordinate is within
  :data:`AMBIGUOUS` of a boundary, and allow each ambiguous sample to move
  (one sample's volume, one unit vector). Random poses almost never have
  one; then the comparison is as tight as for the 2x kernel.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine import events
from bonesim.engine.haptics import O_MAG, O_N_IMMERSED, O_TX, O_TZ, O_VOLUME, make_stencil
from bonesim.engine.haptics_rows import ROWS_MIN_OVERSAMPLE
from bonesim.engine.model import make_model, make_state

from tests.bonesim.fakes import BONE, MATERIALS, NERVE, NO_BUDGET, FakeBurr, block_model
from tests.bonesim.engine.test_haptics import ref_frame, ref_step, run

#: Distance to a voxel boundary [voxels] within which a sample may be
#: assigned either way (see the module docstring).
AMBIGUOUS = 1e-6


def ambiguous_samples(model, pos, axis) -> int:
    """Samples of the model's stencil within :data:`AMBIGUOUS` of a voxel boundary."""
    world = np.asarray(pos, float) + model.stencil.offsets @ ref_frame(axis).T
    q = (world - model.grid.origin_mm) / model.spacing_mm + 0.5
    return int((np.abs(q - np.rint(q)) < AMBIGUOUS).any(axis=1).sum())


def random_model(seed, oversample, radius=1.5):
    rng = np.random.default_rng(seed)
    labels = (rng.random((20, 20, 20)) < 0.6).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.1] = 2
    burr = FakeBurr(radius_mm=radius, k_low=0.5, k_high=2.0, max_force_n=50.0)
    m = make_model(labels, 0.5, [BONE, NERVE], burr, materials=MATERIALS,
                   oversample=oversample,
                       budget_settings=NO_BUDGET)
    return m, labels


# ------------------------------------------------------------- the stencil
@pytest.mark.parametrize("radius,h", [(1.5, 0.125), (3.5, 0.125), (1.0, 0.5 / 3)])
def test_rows_cover_the_stencil_and_their_sums_are_the_samples_sums(radius, h):
    st = make_stencil(radius, h, 4.0, 2.0)
    assert st.row_off[:, 1].sum() == st.n and st.row_off[:, 1].min() >= 1
    at = 0
    for r in range(st.n_rows):
        start, n = st.row_off[r]
        o = st.offsets[at:at + n]
        # consecutive samples, one (o_x, o_y), h apart along z from the head
        assert np.all(o[:, :2] == o[0, :2])
        np.testing.assert_allclose(o[:, 2], st.row_head[r, 2] + h * np.arange(n),
                                   rtol=0, atol=1e-6)
        np.testing.assert_array_equal(st.row_head[r], o[0])
        s = st.row_sums[start:start + n + 1]
        assert np.all(s[0] == 0)
        np.testing.assert_allclose(s[1:, 0], np.cumsum(st.inv_r[at:at + n]), rtol=1e-13)
        np.testing.assert_allclose(s[1:, 1], np.cumsum(o[:, 2] * st.inv_r[at:at + n]),
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(s[1:, 2], np.cumsum(st.lat[at:at + n]), rtol=1e-12)
        at += n
    # mirror images share their sums: about an eighth of the table
    assert len(st.row_sums) < 0.2 * (st.n + st.n_rows) or st.n < 2000


# ------------------------------------------------------- against reference
@settings(max_examples=30, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1),
       pos=hs.tuples(*[hs.floats(2.0, 8.0)] * 3),
       axis=hs.tuples(*[hs.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.2),
       drill=hs.booleans(), direction=hs.sampled_from([-1, 1]),
       oversample=hs.sampled_from([3, 4, 5]))
def test_row_pass_matches_numpy_reference(seed, pos, axis, drill, direction, oversample):
    m, labels = random_model(seed, oversample)
    s = make_state(m)
    dens0, _ = m.grid.to_dense()
    total, tan, mag, vol, new = ref_step(m, dens0, labels, np.array(pos), np.array(axis),
                                         drill, direction)
    got = run(m, s, pos, axis, drill, direction)
    amb = ambiguous_samples(m, pos, axis)
    h3 = m.stencil.sample_volume_mm3
    if amb == 0:
        assert s.out[O_VOLUME] == pytest.approx(vol, rel=1e-12, abs=1e-12)
        assert s.out[O_MAG] == pytest.approx(mag, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(got, total, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(s.out[O_TX:O_TZ + 1], tan, rtol=1e-9, atol=1e-12)
        dens1, _ = s.grid.to_dense()
        np.testing.assert_allclose(dens1, new, rtol=0, atol=2e-7)
        assert s.n_removed == int(((dens0 > 0) & (new == 0)).sum())
    else:
        # each ambiguous sample may add or drop one sample's weighted volume
        assert abs(s.out[O_VOLUME] - vol) <= amb * h3 * m.stiff.max() + 1e-12


@pytest.mark.parametrize("oversample", [3, 4])
def test_no_sample_sits_on_a_boundary_so_the_row_pass_is_the_reference(oversample):
    """Fixed poses away from boundaries: per-voxel removal equals the
    reference's, which checks each voxel's samples one by one (a sample in the
    wrong voxel moves ~1e-3 of density, 2e-7 is allowed)."""
    rng = np.random.default_rng(11)
    n_checked = 0
    for _ in range(12):
        m, labels = random_model(int(rng.integers(1 << 30)), oversample)
        pos = rng.uniform(3.0, 7.0, 3)
        axis = rng.normal(size=3)
        if ambiguous_samples(m, pos, axis):
            continue
        s = make_state(m)
        dens0, _ = m.grid.to_dense()
        total, tan, mag, vol, new = ref_step(m, dens0, labels, pos, axis, True)
        got = run(m, s, pos, axis, True)
        assert s.out[O_VOLUME] == pytest.approx(vol, rel=1e-12)
        np.testing.assert_allclose(got, total, rtol=1e-9, atol=1e-9)
        dens1, _ = s.grid.to_dense()
        np.testing.assert_allclose(dens1, new, rtol=0, atol=2e-7)
        assert np.abs(dens0 - new).max() > 1e-3      # removal visible per sample
        n_checked += 1
    assert n_checked >= 8


# ------------------------------------------------------------ exact truths
@settings(max_examples=20, deadline=None)
@given(pos=hs.tuples(*[hs.floats(7.0, 13.0)] * 3),
       axis=hs.tuples(*[hs.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.2),
       oversample=hs.sampled_from([3, 4, 6]))
def test_burr_inside_bone_immerses_its_whole_stencil(pos, axis, oversample):
    labels = np.ones((40, 40, 40), np.uint8)
    m, s = block_model(labels=labels, burr=FakeBurr(radius_mm=2.0), oversample=oversample,
                       budget_settings=NO_BUDGET)
    f = run(m, s, pos, axis, drill=False)
    assert s.out[O_N_IMMERSED] == m.stencil.n
    assert s.out[O_VOLUME] == pytest.approx(m.stencil.volume_mm3, rel=1e-13)
    # enclosed symmetrically: no direction to push in
    assert np.linalg.norm(f) < 1e-9 * s.out[O_MAG] + 1e-12


@pytest.mark.parametrize("oversample", [3, 4])
def test_burr_outside_bone_feels_nothing(oversample):
    m, s = block_model(burr=FakeBurr(radius_mm=2.0), oversample=oversample,
                       budget_settings=NO_BUDGET)
    top = 20 * 0.5 - 0.25
    f = run(m, s, (10.0, 10.0, top + 2.0 + 1e-3), (0.3, -0.2, -1.0))
    assert s.out[O_N_IMMERSED] == 0 and s.out[O_VOLUME] == 0.0
    assert np.all(f == 0) and s.n_removed == 0


@pytest.mark.parametrize("oversample", [1, 2, 3, 4])
def test_the_row_pass_runs_from_rows_min_oversample_on(oversample, monkeypatch):
    """Recorded sessions (2x) keep the per-sample pass, bit for bit."""
    import bonesim.engine.model as model_mod

    calls = {"rows": 0, "samples": 0}

    def count(name, fn):
        def wrapped(*a):
            calls[name] += 1
            return fn(*a)
        return wrapped

    monkeypatch.setattr(model_mod, "haptic_rows_kernel",
                        count("rows", model_mod.haptic_rows_kernel))
    monkeypatch.setattr(model_mod, "haptic_kernel", count("samples", model_mod.haptic_kernel))
    m, s = block_model(burr=FakeBurr(radius_mm=2.0), oversample=oversample,
                       budget_settings=NO_BUDGET)
    run(m, s, (10.03, 9.97, 9.9), (0.3, -0.2, -1.0))
    assert s.out[O_N_IMMERSED] > 0
    rows = oversample >= ROWS_MIN_OVERSAMPLE
    assert calls == {"rows": int(rows), "samples": int(not rows)}


def test_row_pass_deterministic_bit_identical():
    def go():
        m, s = block_model(burr=FakeBurr(k_low=50, k_high=50), oversample=4,
                       budget_settings=NO_BUDGET)
        rng = np.random.default_rng(7)
        forces = []
        for n in range(150):
            pos = np.array([10.0, 10.0, 10.0]) + rng.normal(0, 0.3, 3)
            forces.append(run(m, s, pos, (0.1, 0.2, -1.0), t=n * 1e-3))
        return s, np.array(forces)
    (a, fa), (b, fb) = go(), go()
    assert a.n_removed > 0
    assert fa.tobytes() == fb.tobytes()
    assert a.grid.density.tobytes() == b.grid.density.tobytes()
    ra, rb = events.removals(a.tissue.read(0)), events.removals(b.tissue.read(0))
    assert all(np.array_equal(ra[k], rb[k]) for k in ra)


def test_row_pass_injuries_on_contact_and_removal():
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :20] = 1
    labels[:, :, 17:20] = 2                              # nerve sheet at the top
    burr = FakeBurr(k_low=1e3, k_high=1e3)
    m, s = block_model(labels=labels, structures=[BONE, NERVE], burr=burr, oversample=4,
                       budget_settings=NO_BUDGET)
    for n in range(0, 300):
        run(m, s, (10.0, 10.0, 10.4), (0, 0, -1.0), t=n * 1e-3)
    inj = events.injuries(s.tissue.read(0))
    assert (inj["kind"] == 0).sum() == 1 and inj["label"][0] == 2
    lost = inj["voxels"][inj["kind"] == 1].sum()
    assert lost > 0 and lost == s.removed_by_label[2]
