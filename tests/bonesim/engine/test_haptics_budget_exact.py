"""The fixed-budget haptic step is bit for bit the step recorded sessions
were made with.

:mod:`tests.bonesim.engine.haptics_budget_previous` holds the budget kernel
as it was before its speed-up; every test here steps two states of one
model, one with :func:`bonesim.engine.haptics_budget.budget_step` (the kernel
with the arguments the state keeps) and one with the frozen copy of the
kernel (swapped in where :func:`bonesim.engine.model.step` calls the
step), and compares every array the step writes (force, outputs, event
rings, the carried doses, thresholds, counts and queue, touched flags,
densities) as bytes after every step.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine import model as model_mod
from bonesim.engine.bodies import publish_pose, publish_split
from bonesim.engine.haptics_budget import STEP_FIELDS
from bonesim.engine.model import Sample, make_model, make_state, step

from tests.bonesim.engine.haptics_budget_previous import previous_budget_kernel as _frozen
from tests.bonesim.fakes import BONE, MATERIALS, NERVE, FakeBurr


def previous_budget_step(m, state):
    """The frozen kernel in :func:`bonesim.engine.haptics_budget.budget_step`'s
    place for ``state``'s passes (burr 0): its arguments taken afresh from
    the state and the model (not through the step's kept
    :class:`~bonesim.engine.haptics_budget.StepArgs`), without the new
    kernel's last two scratch arrays (``lbkey``, the record of its brick
    table: the frozen kernel fills its table on every pass; ``row_a``)."""
    g = STEP_FIELDS.index("group")

    def step_(a, pos, axis, drill, direction, speed_factor, dt, t, gsel, owner, first, last):
        f = model_mod.budget_arrays(m, state, 0)
        assert STEP_FIELDS[-2:] == ("lbkey", "row_a") and len(f) == len(STEP_FIELDS)
        _frozen(*f[:g], pos, axis, drill, direction, speed_factor, dt, t, f[g], gsel, owner,
                first, last, *f[g + 1:-2])
    return step_


#: Records of the compared states' event rings (a power of two).
_RING = 1 << 12
#: Voxel layers ``k < _TOP`` hold the random blocks' bone.
_TOP = 24
_SHAPE = (44, 44, 36)


def _written(state) -> dict:
    """Every array a budget step writes, by name (rings in full)."""
    g, bs = state.grid, state._budget
    arrays = {"density": g.density, "label": g.label, "body": state.body,
              "touched_flag": state.touched_flag, "out": state.out, "force": state.force_n,
              "removed_by_label": state.removed_by_label,
              "prev_contact": state._prev_contact, "contact": state._contact,
              "lost": state._lost, "lab_body": state._lab_body,
              "onset_body": state._onset_body, "counts": state._counts,
              "tissue_head": state.tissue.head, "touched_head": state.touched.head,
              "dose": bs.dose, "thr": bs.thr, "occ": bs.occ, "queued": bs.queued,
              "rep": bs.rep, "queue": bs.queue, "qhead": bs.qhead}
    for ring in ("tissue", "touched"):
        for k, v in getattr(state, ring).fields.items():
            arrays[f"{ring}.{k}"] = v
    return arrays


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).reshape(-1).view(np.uint8)


def _assert_same(new, old, q) -> None:
    a, b = _written(new), _written(old)
    for k in a:
        assert np.array_equal(_bits(a[k]), _bits(b[k])), f"{k} differs after step {q}"


def _random_model(seed, voxel, radius, removal_voxels=None):
    rng = np.random.default_rng(seed)
    labels = np.zeros(_SHAPE, np.uint8)
    labels[:, :, :_TOP] = 1
    labels[rng.random(_SHAPE) < 0.2] = 0                      # pores
    labels[(rng.random(_SHAPE) < 0.08) & (labels > 0)] = 2     # a nerve's voxels
    # strong enough that a few steps' doses remove cells
    burr = FakeBurr(radius_mm=radius, k_low=20.0, k_high=60.0, max_force_n=8.0,
                    r_max=50.0 + 150.0 * rng.random(), falloff=20.0 + 20.0 * rng.random())
    m = make_model(labels, voxel, [BONE, NERVE], burr, materials=MATERIALS)
    assert m.budget.binding
    if removal_voxels is not None:
        m = replace(m, budget=replace(m.budget, removal_voxels=(removal_voxels,)))
    return m


def _poses(rng, m, n, drill, direction):
    """A walk near the block's top face, x and y central."""
    v = m.spacing_mm
    sh = np.array(m.grid.shape)
    pos = m.grid.origin_mm + v * np.array([sh[0] / 2, sh[1] / 2, _TOP - 0.5])
    pos = pos + np.array([rng.normal(0, 0.4), rng.normal(0, 0.4), rng.uniform(-0.6, 0.2)])
    out = []
    for q in range(n):
        pos = pos + rng.normal(0, 0.08, 3)
        ax = rng.normal(size=3)
        ax /= np.linalg.norm(ax)
        on = drill if q < n - 4 else False                   # the last steps only flush
        out.append(Sample(q * 1e-3, pos.copy(), ax, on, 60000.0 * (0.5 + rng.random()),
                          direction))
    return out


def _run_both(m, prepare, samples, monkeypatch):
    """Step two fresh states (``prepare`` applied to each) through
    ``samples``, the new kernel and the frozen one; compare after every
    step. Returns the immersed samples and the voxels removed.

    The rings hold :data:`_RING` records (more would wrap, as a ring does), so
    comparing them whole after every step is cheap."""
    new, old = make_state(m, ring_capacity=_RING), make_state(m, ring_capacity=_RING)
    prepare(new)
    prepare(old)
    immersed = 0
    for q, smp in enumerate(samples):
        step(m, new, smp)
        with monkeypatch.context() as mp:
            mp.setattr(model_mod, "budget_step", previous_budget_step(m, old))
            step(m, old, smp)
        _assert_same(new, old, q)
        immersed += new.out[8]
    return immersed, new.n_removed


@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), voxel=hs.sampled_from([0.1, 0.13, 0.19]),
       radius=hs.sampled_from([0.6, 1.0, 1.5]), drill=hs.booleans(),
       direction=hs.sampled_from([-1, 1]),
       removal_voxels=hs.sampled_from([None, 1, 40]))
def test_budget_kernel_is_the_previous_kernel_bit_for_bit(seed, voxel, radius, drill,
                                                          direction, removal_voxels):
    m = _random_model(seed, voxel, radius, removal_voxels)
    rng = np.random.default_rng(seed + 1)
    with pytest.MonkeyPatch.context() as mp:
        immersed, removed = _run_both(m, lambda s: None, _poses(rng, m, 30, drill, direction),
                                      mp)
    assert immersed > 0                           # the burr was in the bone
    assert removed > 0 or not drill               # and removed some while drilling


@settings(max_examples=8, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), voxel=hs.sampled_from([0.1, 0.19]),
       shift=hs.floats(-1.0, 1.0))
def test_bodies_passes_are_the_previous_kernel_bit_for_bit(seed, voxel, shift):
    """Two bodies, one at another pose: passes that see one group only, doses
    owned by each pass's body, steps out of reach that only flush."""
    m = _random_model(seed, voxel, 1.0)
    sh = m.grid.shape

    def prepare(st):
        g = np.mgrid[0:sh[0], 0:sh[1] // 2, 0:sh[2]].reshape(3, -1).T.astype(np.int32)
        publish_split(st, 0, g, 0.0)
        publish_pose(st, 1, (shift, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), 0.0)

    rng = np.random.default_rng(seed)
    smp = _poses(rng, m, 24, True, 1)
    far = [Sample(1.0 + q * 1e-3, np.array([-30.0, -30.0, 30.0]), np.array([0.0, 0.0, -1.0]),
                  False, 60000.0, 1) for q in range(4)]
    with pytest.MonkeyPatch.context() as mp:
        immersed, removed = _run_both(m, prepare, smp + far, mp)
    assert immersed > 0 and removed > 0
