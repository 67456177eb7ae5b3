"""The per-sample haptic kernel is bit for bit the kernel recorded sessions
were made with.

:mod:`tests.bonesim.engine.haptics_previous` holds the kernel as it was
before the row walk; every test here steps two states of one model, one with
the kernel of :mod:`bonesim.engine.haptics` and one with the frozen copy
(swapped in where :func:`bonesim.engine.model.step` calls the kernel), and
compares every output and every array the step writes, as bytes.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine import model as model_mod
from bonesim.engine.bodies import publish_pose, publish_split
from bonesim.engine.model import Sample, make_model, make_state, step

from tests.bonesim.engine.haptics_previous import previous_haptic_kernel, previous_rows_kernel
from tests.bonesim.fakes import BONE, MATERIALS, NERVE, NO_BUDGET, FakeBurr

#: Position of ``row_off`` among :func:`bonesim.engine.haptics.haptic_kernel`'s
#: arguments (the frozen kernel has none).
_ROW_OFF_ARG = 12
#: The random blocks' bone fills the voxel layers ``k < _TOP``.
_TOP = 16


def _previous(*args):
    return previous_haptic_kernel(*args[:_ROW_OFF_ARG], *args[_ROW_OFF_ARG + 1:])


def _written(state) -> dict:
    """Every array a step writes, by name; the rings up to their heads (the
    rest of a ring is never written before the head gets there)."""
    g = state.grid
    arrays = {"density": g.density, "label": g.label, "body": state.body,
              "touched_flag": state.touched_flag, "out": state.out, "force": state.force_n,
              "removed_by_label": state.removed_by_label,
              "prev_contact": state._prev_contact, "contact": state._contact,
              "lost": state._lost, "acc": state._acc, "tissue_head": state.tissue.head,
              "touched_head": state.touched.head}
    for ring in ("tissue", "touched"):
        r = getattr(state, ring)
        for k, v in r.fields.items():
            arrays[f"{ring}.{k}"] = v[:min(int(r.head[0]), len(v))]
    return arrays


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).reshape(-1).view(np.uint8)


def _assert_same(new, old) -> None:
    """The two states' written arrays agree bit for bit (NaN and -0.0 too)."""
    a, b = _written(new), _written(old)
    for k in a:
        assert np.array_equal(_bits(a[k]), _bits(b[k])), f"{k} differs"


def _random_model(seed, radius, oversample, spacing=0.5, shape=(28, 28, 28), **kw):
    rng = np.random.default_rng(seed)
    labels = np.zeros(shape, np.uint8)
    labels[:, :, :_TOP] = 1
    labels[rng.random(shape) < 0.25] = 0                  # pores
    labels[(rng.random(shape) < 0.08) & (labels > 0)] = 2    # a nerve's voxels
    burr = FakeBurr(radius_mm=radius, k_low=0.5, k_high=2.0, max_force_n=50.0,
                    r_max=4.0 + rng.random(), falloff=2.0 + rng.random())
    return make_model(labels, spacing, [BONE, NERVE], burr, materials=MATERIALS,
                      oversample=oversample, **kw)


def _run_both(m, prepare, samples, monkeypatch, name="haptic_kernel", previous=_previous):
    """Step two fresh states (``prepare`` applied to each) through ``samples``,
    one with the kernel ``name`` of :mod:`bonesim.engine.model` and one with
    ``previous`` in its place; assert they agree after every step."""
    new, old = make_state(m), make_state(m)
    prepare(new)
    prepare(old)
    immersed = 0
    for smp in samples:
        step(m, new, smp)
        with monkeypatch.context() as mp:
            mp.setattr(model_mod, name, previous)
            step(m, old, smp)
        _assert_same(new, old)
        immersed += new.out[8]
    for ring in ("tissue", "touched"):             # and nothing written past the heads
        for k, v in getattr(new, ring).fields.items():
            assert np.array_equal(_bits(v), _bits(getattr(old, ring).fields[k])), k
    return immersed


def _poses(rng, m, n, drill, direction):
    # near the block's top face (bone below voxel layer ``_TOP``), x and y central
    sh = np.array(m.grid.shape)
    pos = m.grid.origin_mm + m.spacing_mm * np.array([sh[0] / 2, sh[1] / 2, _TOP - 0.5])
    pos = pos + np.array([rng.normal(0, 1.5), rng.normal(0, 1.5), rng.uniform(-1.0, 0.5)])
    out = []
    for q in range(n):
        pos = pos + rng.normal(0, 0.2, 3)
        ax = rng.normal(size=3)
        ax /= np.linalg.norm(ax)
        out.append(Sample(q * 1e-3, pos.copy(), ax, drill, 60000.0 * (0.5 + rng.random()),
                          direction))
    return out


@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), radius=hs.sampled_from([1.0, 1.5, 3.5]),
       oversample=hs.sampled_from([1, 2]), drill=hs.booleans(),
       direction=hs.sampled_from([-1, 1]))
def test_kernel_is_the_previous_kernel_bit_for_bit(seed, radius, oversample, drill,
                                                   direction):
    m = _random_model(seed, radius, oversample)
    rng = np.random.default_rng(seed + 1)
    with pytest.MonkeyPatch.context() as mp:
        immersed = _run_both(m, lambda s: None, _poses(rng, m, 12, drill, direction), mp)
    assert immersed > 0                 # the burr was in the bone


@settings(max_examples=10, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), shift=hs.floats(-2.0, 2.0))
def test_bodies_pass_is_the_previous_kernel_bit_for_bit(seed, shift):
    """Several bodies, one at another pose: passes that see one group only."""
    m = _random_model(seed, 1.5, 2)
    sh = m.grid.shape

    def prepare(st):
        g = np.mgrid[0:sh[0], 0:sh[1] // 2, 0:sh[2]].reshape(3, -1).T.astype(np.int32)
        publish_split(st, 0, g, 0.0)
        publish_pose(st, 1, (shift, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), 0.0)

    rng = np.random.default_rng(seed)
    with pytest.MonkeyPatch.context() as mp:
        immersed = _run_both(m, prepare, _poses(rng, m, 10, True, 1), mp)
    assert immersed > 0


def test_seven_mm_sweep_is_the_previous_kernel_bit_for_bit(monkeypatch):
    """The bench's sweep (7 mm burr half immersed in a block, 2x): 200 steps."""
    labels = np.zeros((40, 40, 30), np.uint8)
    labels[:, :, :20] = 1
    m = make_model(labels, 0.5, [BONE], FakeBurr(radius_mm=3.5, max_force_n=10.0),
                   materials=MATERIALS)
    top = m.grid.origin_mm[2] + 20 * 0.5 - 0.25
    axis = np.array([0.3, 0.0, -1.0])
    smp = [Sample(q * 1e-3, np.array([5.0 + 0.08 * q, 10.0, top]), axis, True, 60000.0, 1)
           for q in range(200)]
    assert _run_both(m, lambda s: None, smp, monkeypatch) > 0


@settings(max_examples=10, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), oversample=hs.sampled_from([3, 4]),
       drill=hs.booleans())
def test_row_kernel_on_the_new_pass_ends_is_bit_for_bit_what_it_was(seed, oversample,
                                                                    drill):
    """The row kernel (3x and more) shares the start and end of a pass
    (gather, removal), which changed: it too must give the same bits."""
    m = _random_model(seed, 1.5, oversample, budget_settings=NO_BUDGET)
    assert m.oversample >= 3 and not m.budget.binding
    rng = np.random.default_rng(seed + 2)
    with pytest.MonkeyPatch.context() as mp:
        immersed = _run_both(m, lambda s: None, _poses(rng, m, 8, drill, 1), mp,
                             "haptic_rows_kernel", previous_rows_kernel)
    assert immersed > 0
