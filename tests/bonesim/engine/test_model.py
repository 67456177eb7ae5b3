"""Model / State / step on the real phantom: immutability and bit-exact replay."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.io.burrs import load_burr
from bonesim.io.loading import load_model
from bonesim.engine.model import make_state, step
from tests.bonesim.plans import drilling_window


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-4mm")


@pytest.fixture(scope="module")
def samples():
    # the first 3 s that actually drill bone
    traj = drilling_window("cutting-4mm", 300).resample(1000.0)
    return list(traj.samples())[:3000]


def _run(model, samples):
    state = make_state(model)
    forces = np.array([step(model, state, s).copy() for s in samples])
    return state, forces


def test_model_is_immutable_and_states_are_independent(model, samples):
    before = model.grid.density.copy()
    assert not model.grid.density.flags.writeable
    assert not model.stencil.packed.flags.writeable and not model.params.flags.writeable
    with pytest.raises(ValueError):
        model.grid.density[0, 0] = 0.5
    s1, _ = _run(model, samples)
    s2 = make_state(model)
    assert s1.n_removed > 0
    np.testing.assert_array_equal(model.grid.density, before)
    np.testing.assert_array_equal(s2.grid.density, before)


def test_replay_is_bit_identical(model, samples):
    a, fa = _run(model, samples)
    b, fb = _run(model, samples)
    assert a.n_removed > 30
    assert a.grid.density.tobytes() == b.grid.density.tobytes()
    assert fa.tobytes() == fb.tobytes()
    ra, rb = events.removals(a.tissue.read(0)), events.removals(b.tissue.read(0))
    for key in ra:
        assert ra[key].tobytes() == rb[key].tobytes()


def test_burr_change_keeps_the_bone(model, samples):
    state, _ = _run(model, samples[:1500])
    removed = state.n_removed
    other = model.with_burr(load_burr("diamond-2mm"))
    state.fit_scratch(other)
    for s in samples[1500:]:
        step(other, state, s)
    assert other.grid is model.grid and other.stencil.n < model.stencil.n
    assert state.n_removed >= removed


def test_model_sent_to_another_process_stays_read_only(model):
    # the haptic loop and the recorder get the model pickled; its arrays must
    # keep their read-only numba types there, or the loop's first step
    # compiles a second kernel that warmup() never built
    import pickle

    import numba

    copy = pickle.loads(pickle.dumps(model))
    pairs = [(model.grid.density, copy.grid.density), (model.grid.label, copy.grid.label)]
    pairs += [(getattr(model, k), getattr(copy, k))
              for k in ("stiff", "removal", "injury", "colors", "params")]
    pairs += [(getattr(model.stencil, k), getattr(copy.stencil, k))
              for k in ("offsets", "inv_r", "lat", "packed")]
    for a, b in pairs:
        assert not b.flags.writeable
        assert numba.typeof(b) == numba.typeof(a)
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        copy.grid.label[0, 0] = 2
