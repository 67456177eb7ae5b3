"""Visibility at removal: the DDA walk against an exact segment/box reference,
analytic cases, and the tracker's ordering and reset rules."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.engine import events
from bonesim.engine.grid import Grid
from bonesim.engine.model import make_model
from bonesim.physics.visibility import VisibilityTracker, judge_removals, occluders

from tests.bonesim.fakes import MATERIALS, FakeBurr, FakeStructure

BONE = SimpleNamespace(name="bone", kind="bone")
SOFT = SimpleNamespace(name="dura", kind="soft")
OCC = occluders([BONE, SOFT])                  # label 1 blocks, label 2 does not


def _segment_hits_box(p0, p1, lo, hi) -> bool:
    """Slab test: does the closed segment p0-p1 meet the box [lo, hi]?"""
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for a in range(3):
        if d[a] == 0.0:
            if p0[a] < lo[a] or p0[a] > hi[a]:
                return False
            continue
        u, v = (lo[a] - p0[a]) / d[a], (hi[a] - p0[a]) / d[a]
        u, v = min(u, v), max(u, v)
        t0, t1 = max(t0, u), min(t1, v)
        if t0 > t1:
            return False
    return True


def _reference_visible(labels, spacing, origin, ijk, eye, tool, r) -> int:
    """Every voxel the segment touches, by brute force over the whole grid."""
    p0 = np.asarray(ijk, float)                       # voxel coordinates: centre = index
    p1 = (np.asarray(eye) - origin) / spacing
    for idx in np.argwhere(labels > 0):
        if tuple(idx) == tuple(ijk) or OCC[labels[tuple(idx)]] == 0:
            continue
        centre = origin + spacing * idx
        if np.sum((centre - tool) ** 2) <= r * r:
            continue
        if _segment_hits_box(p0, p1, idx - 0.5, idx + 0.5):
            return 0
    return 1


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), fill=st.floats(0.02, 0.3))
def test_dda_matches_exact_segment_box_reference(seed, fill):
    rng = np.random.default_rng(seed)
    shape = (10, 11, 9)
    labels = np.where(rng.random(shape) < fill, rng.integers(1, 3, shape), 0).astype(np.uint8)
    spacing, origin = 0.5, np.array([-1.0, 2.0, 0.5])
    ijk = rng.integers(0, shape)
    labels[tuple(ijk)] = 1
    # eyes inside and outside the grid, tools anywhere
    eye = origin + spacing * (rng.random(3) * np.array(shape) * 3 - np.array(shape))
    tool = origin + spacing * rng.random(3) * np.array(shape)
    r = float(rng.uniform(0.0, 2.0))
    grid = Grid.from_dense(labels, None, spacing, origin)
    got = judge_removals(grid, OCC, [ijk], [eye], [tool], [r])[0]
    assert got == _reference_visible(labels, spacing, origin, ijk, eye, tool, r)


def _slab_grid():
    """Bone floor z < 6, a bone lid at z = 12; voxel (8, 8, 5) on the floor."""
    labels = np.zeros((16, 16, 16), np.uint8)
    labels[:, :, :6] = 1
    labels[:, :, 12] = 1
    return labels


def test_bone_between_voxel_and_eye_hides_and_contact_or_soft_does_not():
    labels = _slab_grid()
    far_tool = np.array([100.0, 100.0, 100.0])
    eye_above = np.array([8.0, 8.0, 40.0])            # through the lid
    eye_between = np.array([8.0, 8.0, 10.0])          # under the lid
    g = Grid.from_dense(labels, None, 1.0)
    assert judge_removals(g, OCC, [[8, 8, 5]], [eye_between], [far_tool], [1.0])[0] == 1
    g = Grid.from_dense(labels, None, 1.0)
    assert judge_removals(g, OCC, [[8, 8, 5]], [eye_above], [far_tool], [1.0])[0] == 0
    # the lid is soft tissue: not an occluder
    soft = labels.copy()
    soft[:, :, 12] = 2
    g = Grid.from_dense(soft, None, 1.0)
    assert judge_removals(g, OCC, [[8, 8, 5]], [eye_above], [far_tool], [1.0])[0] == 1
    # the burr sits in the lid right above: the lid voxels it touches do not count
    g = Grid.from_dense(labels, None, 1.0)
    assert judge_removals(g, OCC, [[8, 8, 5]], [eye_above], [[8.0, 8.0, 12.0]], [2.0])[0] == 1
    # undercutting: the voxel is seen sideways under an overhang
    g = Grid.from_dense(labels, None, 1.0)
    assert judge_removals(g, OCC, [[8, 8, 5]], [[8.0, -30.0, 5.0]], [far_tool], [1.0])[0] == 0


def test_removals_are_judged_in_order_against_the_tissue_they_leave():
    labels = np.zeros((8, 8, 8), np.uint8)
    labels[4, 4, 1:5] = 1                              # a column under the eye
    eye = [4.0, 4.0, 30.0]
    tool = [50.0, 50.0, 50.0]
    col = [[4, 4, 4], [4, 4, 3], [4, 4, 2], [4, 4, 1]]
    g = Grid.from_dense(labels, None, 1.0)
    # top down: each voxel is visible once the ones above are gone
    assert judge_removals(g, OCC, col, [eye] * 4, [tool] * 4, [1.0] * 4).tolist() == [1] * 4
    g = Grid.from_dense(labels, None, 1.0)
    # bottom up: every voxel but the top one is hidden by the ones above
    got = judge_removals(g, OCC, col[::-1], [eye] * 4, [tool] * 4, [1.0] * 4)
    assert got.tolist() == [0, 0, 0, 1]
    assert g.occupied_count() == 0                     # each was removed after judging


def _removals(t, ijk) -> dict:
    ev = events.empty_events(len(t))
    ev["t_s"][:], ev["ijk"][:] = t, ijk
    return ev


def test_tracker_uses_step_tool_camera_and_resets_from_the_stream():
    labels = np.zeros((8, 8, 8), np.uint8)
    labels[4, 4, 1:5] = 1
    model = make_model(labels, 1.0, [FakeStructure("bone", "bone")],
                       FakeBurr(radius_mm=0.4), materials=MATERIALS, oversample=4)
    tr = VisibilityTracker([model], eye_mm=[4.0, 4.0, 30.0])
    grid = tr.replica.grid
    before = grid.density.copy()
    tr.warm()                                        # loads the kernels, judges nothing
    assert np.array_equal(grid.density, before) and tr.replica.epoch == 0
    tr.add_samples({"t_s": np.array([0.0, 1.0]), "pos_mm": np.full((2, 3), 50.0),
                    "burr": np.zeros(2, np.uint8), "epoch": np.zeros(2, np.int32)})
    rem = _removals([0.0, 0.0, 1.0], [[4, 4, 1], [4, 4, 2], [4, 4, 3]])
    assert tr.judge(rem).tolist() == [0, 0, 0]       # bottom up, under the top voxel
    # now the camera looks from below: without a reset (4, 4, 4) would be in
    # plain view, but the reset put the column back in front of it
    tr.add_camera({"t_s": np.array([1.5]), "eye_mm": np.array([[4.0, 4.0, -30.0]])})
    tr.add_samples({"t_s": np.array([2.0]), "pos_mm": np.full((1, 3), 50.0),
                    "burr": np.zeros(1, np.uint8), "epoch": np.ones(1, np.int32)})
    batch = events.concat([events.empty_events(1), _removals([2.0], [[4, 4, 4]])])
    batch["kind"][0], batch["t_s"][0], batch["n"][0] = events.RESET, 2.0, 1
    assert tr.judge(batch).tolist() == [-1, 0]        # the reset is no removal
    assert tr.replica.epoch == 1
    # without the reset, from below, it would have been in view
    tr2 = VisibilityTracker([model], eye_mm=[4.0, 4.0, -30.0])
    tr2.add_samples({"t_s": np.array([0.0, 1.0]), "pos_mm": np.full((2, 3), 50.0),
                     "burr": np.zeros(2, np.uint8), "epoch": np.zeros(2, np.int32)})
    tr2.judge(_removals([0.0, 0.0, 1.0], [[4, 4, 1], [4, 4, 2], [4, 4, 3]]))
    assert tr2.judge(_removals([1.0], [[4, 4, 4]])).tolist() == [1]
