"""One replica: applying the tissue-event stream reproduces the producer's tissue."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import publish_pose, publish_split
from bonesim.engine.model import Sample, make_state, reset_state, step
from bonesim.engine.replica import TissueReplica
from bonesim.engine.surface import Surface

from tests.bonesim.fakes import BONE, NERVE, block_model

AXIS = np.array([0.0, 0.0, -1.0])


def _same_tissue(a, b) -> None:
    np.testing.assert_array_equal(a.grid.density == 0, b.grid.density == 0)
    for name in ("body", "pose", "pose_m", "alive", "bounds", "removed_by_label"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _scripted_run(seed: int):
    """A producer's run with drilling, resets, splits and poses; returns the
    model, the producer state and (event count, tissue snapshot) at every
    reset and at the end."""
    rng = np.random.default_rng(seed)
    labels = np.zeros((40, 40, 30), np.uint8)
    labels[:, :, :20] = 1
    labels[12:20, 12:20, 14:18] = 2
    m, st = block_model(labels=labels, structures=[BONE, NERVE])
    marks = []
    t = 0.0
    for phase in range(3):
        for q in range(400):
            t += 1e-3
            x = 6.0 + 8.0 * q / 400 + rng.normal(0, 0.05)
            step(m, st, Sample(t, np.array([x, 8.0 + 2 * phase, 9.3]), AXIS, True,
                               60000.0, 1))
            if q == 150:
                lo = rng.integers(0, 20)
                box = np.mgrid[lo:lo + 12, 0:40, 0:20].reshape(3, -1).T
                publish_split(st, 0, box, t)
            if q == 250 and st.alive[1]:
                publish_pose(st, 1, (0.0, 0.0, 0.5 * (phase + 1), 1.0, 0.0, 0.0, 0.0), t)
        snap = make_state(m, ring_capacity=16)
        for name in ("body", "pose", "pose_m", "alive", "bounds", "removed_by_label"):
            getattr(snap, name)[:] = getattr(st, name)
        snap.grid.density[:] = st.grid.density
        marks.append((st.tissue.count, snap))
        if phase < 2:                                 # the loop's reset
            t += 1e-3
            reset_state(m, st, rings=False)
            events.push_event(st.tissue, events.RESET, t, n=phase + 1)
    return m, st, marks


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_replica_fed_in_chunks_equals_the_producer_at_every_reset_and_the_end(seed):
    m, st, marks = _scripted_run(seed)
    ev = st.tissue.read(0)
    kinds = set(np.unique(ev["kind"]).tolist())
    assert {events.REMOVED, events.SPLIT, events.POSE, events.RESET} <= kinds
    rng = np.random.default_rng(seed + 10)
    rep = TissueReplica(m)
    pos = 0
    for count, snap in marks:
        while pos < count:                            # chunks of any size
            n = int(min(count - pos, rng.integers(1, 3000)))
            rep.apply({k: a[pos:pos + n] for k, a in ev.items()})
            pos += n
        _same_tissue(rep.state, snap)
    assert rep.epoch == 2 and rep.applied == len(ev["kind"])


def test_following_replica_keeps_its_surface_exact_across_a_reset():
    m, st = block_model()
    rep = TissueReplica(m, st, surface=True)
    t = 0.0
    resets = 0
    for phase in range(2):
        for q in range(300):
            t += 1e-3
            step(m, st, Sample(t, np.array([5.0 + 0.02 * q, 10.0, 9.3]), AXIS, True,
                               60000.0, 1))
            if q % 16 == 15:
                resets += rep.drain().reset
        if phase == 0:
            reset_state(m, st, rings=False)
            events.push_event(st.tissue, events.RESET, t, n=1)
    resets += rep.drain().reset
    assert resets == 1 and rep.epoch == 1
    np.testing.assert_array_equal(rep.grid.density, st.grid.density)
    fresh = Surface.of_model(m, rep.grid)
    assert not fresh.canonical().differences(rep.surface.canonical())


def test_changes_report_injuries_after_the_last_reset_only():
    labels = np.zeros((40, 40, 30), np.uint8)
    labels[:, :, :20] = 1
    labels[15:25, 15:25, 16:20] = 2
    m, st = block_model(labels=labels, structures=[BONE, NERVE])
    rep = TissueReplica(m, st)
    over = np.array([10.0, 10.0, 9.6])
    step(m, st, Sample(0.001, over, AXIS, True, 60000.0, 1))
    assert len(rep.drain().injuries["t_s"]) == 1
    step(m, st, Sample(0.002, over + [0, 0, 5.0], AXIS, True, 60000.0, 1))
    step(m, st, Sample(0.003, over, AXIS, True, 60000.0, 1))     # contact again
    reset_state(m, st, rings=False)
    events.push_event(st.tissue, events.RESET, 0.004, n=1)
    ch = rep.drain()
    assert ch.reset and len(ch.injuries["t_s"]) == 0
    with pytest.raises(ValueError, match="follows no live state"):
        TissueReplica(m).drain()
