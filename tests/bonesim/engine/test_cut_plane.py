"""The cut plane: a stroke removes exactly the voxels its rays pass, in each
body's own frame, published as tissue events a replica follows."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as hs

from bonesim.engine import events
from bonesim.engine.bodies import pose_matrix, publish_pose, publish_split_box
from bonesim.engine.cut_plane import (plane_axes, plane_pose, publish_cut, quantize_size,
                                      sample_offsets)
from bonesim.engine.model import make_state, reset_state
from bonesim.engine.replica import TissueReplica
from bonesim.io.loading import load_model


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def state(model):
    return make_state(model)


def _ray_voxels(y0, dy, length, lo, hi):
    """Reference: every voxel (index frame shifted by 1/2, voxel i spans [i,
    i+1)) of the box lo..hi in which the segment y0 + t dy, t in [0,
    length], has positive length, by the slab test on each candidate voxel."""
    y1 = y0 + length * dy
    a0 = np.maximum(np.floor(np.minimum(y0, y1)).astype(int) - 1, lo)
    a1 = np.minimum(np.floor(np.maximum(y0, y1)).astype(int) + 1, hi)
    if (a1 < a0).any():
        return []
    ii = np.stack(np.meshgrid(*[np.arange(a0[a], a1[a] + 1) for a in range(3)],
                              indexing="ij"), -1).reshape(-1, 3)
    tlo = np.zeros(len(ii))
    thi = np.full(len(ii), float(length))
    for a in range(3):
        if dy[a] == 0.0:
            inside = (ii[:, a] <= y0[a]) & (y0[a] < ii[:, a] + 1)
            thi = np.where(inside, thi, -1.0)
            continue
        ta = (ii[:, a] - y0[a]) / dy[a]
        tb = (ii[:, a] + 1 - y0[a]) / dy[a]
        tlo = np.maximum(tlo, np.minimum(ta, tb))
        thi = np.minimum(thi, np.maximum(ta, tb))
    hit = thi > tlo
    order = np.argsort(tlo[hit], kind="stable")
    return [tuple(v) for v in ii[hit][order]]


def _along_a_face(y0, dy, length):
    """Whether a ray runs within 1e-9 voxel along a voxel face (parallel to
    it, on it): which of the two voxels it removes there is a rounding tie
    of the last bit, not a rule the reference can state."""
    on = np.abs(y0 - np.rint(y0)) < 1e-9
    flat = np.abs(dy) * max(length, 1.0) < 1e-9
    return bool(np.any(on & flat))


def _reference(model, state, pose, w, h, d):
    """Slow reference of one stroke: ``[(body, i, j, k)]`` of the voxels it
    removes, in the order the stroke visits them, from the state before it;
    None when a ray runs along a voxel face (:func:`_along_a_face`)."""
    g = state.grid
    sp = g.spacing_mm
    axes = plane_axes(pose)
    su, sv = sample_offsets(w, sp), sample_offsets(h, sp)
    shape = np.asarray(g.shape)
    out, seen = [], set()
    for b in np.flatnonzero(state.alive):
        m = state.pose_m[b]
        R, t = m[:, :3], m[:, 3]
        cb = R.T @ (pose[:3] - t)
        ub, vb, nb = R.T @ axes[0], R.T @ axes[1], R.T @ axes[2]
        lo = np.maximum(state.bounds[b, :3], 0)
        hi = np.minimum(state.bounds[b, 3:], shape - 1)
        for p, q in itertools.product(su, sv):
            y0 = (cb + p * ub + q * vb - g.origin_mm) / sp + 0.5
            if _along_a_face(y0, nb / sp, d):
                return None
            for ijk in _ray_voxels(y0, nb / sp, d, lo, hi):
                key = (int(b),) + tuple(int(x) for x in ijk)
                if key in seen:
                    continue
                if _material(state, ijk) and _body_of(state, ijk) == b:
                    seen.add(key)
                    out.append(key)
    return out


def _material(state, ijk):
    g = state.grid
    from bonesim.engine.grid import density_at
    return density_at(g.keys, g.vals, g.density_ro, *map(int, ijk)) > 0


def _body_of(state, ijk):
    from bonesim.engine.bodies import voxel_bodies
    return int(voxel_bodies(state.grid, state.body, np.array([ijk]), none=255)[0])


def _removed(state, start):
    ev = state.tissue.read(start)
    r = ev["kind"] == events.REMOVED
    return [(int(b),) + tuple(int(x) for x in ijk)
            for b, ijk in zip(ev["body"][r], ev["ijk"][r])], ev


def _centre(model):
    g = model.grid
    return np.asarray(g.origin_mm) + (np.asarray(g.shape) - 1) * g.spacing_mm / 2


def _random_pose(centre, rng_vals):
    q = np.asarray(rng_vals[3:7])
    q = q / np.linalg.norm(q)
    return np.concatenate([centre + np.asarray(rng_vals[:3]), q])


quat = hs.lists(hs.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 0.2)
offset = hs.lists(hs.floats(-12, 12), min_size=3, max_size=3)
size = hs.floats(0.0, 3.5)


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(off=offset, q=quat, w=size, h=size, d=hs.floats(0.0, 4.0), moved=hs.booleans(),
       bq=quat, boff=hs.lists(hs.floats(-4, 4), min_size=3, max_size=3))
def test_a_stroke_removes_exactly_the_voxels_its_rays_pass(model, state, off, q, w, h, d,
                                                           moved, bq, boff):
    reset_state(model, state, rings=False)
    c = _centre(model)
    if moved:                   # a block of bone made its own body and moved
        ijk = np.rint((c - model.grid.origin_mm) / model.spacing_mm).astype(int)
        publish_split_box(state, 0, ijk - 10, ijk + 10, 0.0)
        bq = np.asarray(bq) / np.linalg.norm(bq)
        publish_pose(state, 1, np.concatenate([np.asarray(boff), bq]), 0.0)
    pose = _random_pose(c, list(off) + list(q))
    w, h, d = (float(x) * 1e-3 for x in quantize_size(w, h, d))
    ref = _reference(model, state, pose, w, h, d)
    assume(ref is not None)
    start = state.tissue.count
    before = state.removed_by_label.sum()
    n = publish_cut(state, model.injury, pose, w, h, d, 1.0)
    got, ev = _removed(state, start)
    assert got == ref
    assert n == len(ref) == state.removed_by_label.sum() - before
    # every removed voxel is empty now; the CUT record closes the stroke
    assert all(not _material(state, k[1:]) for k in got)
    assert ev["kind"][-1] == events.CUT and ev["n"][-1] == n
    np.testing.assert_array_equal(ev["value"][-1], pose)
    np.testing.assert_array_equal(ev["ijk"][-1], np.rint(np.array([w, h, d]) * 1e3))


def test_a_stroke_on_a_moved_body_cuts_it_where_it_stands(model, state):
    """A block split off and moved 30 mm along x is cut where it stands now:
    the same stroke shifted with it removes the same voxels of that body, and
    none of the bone it was cut from."""
    reset_state(model, state, rings=False)
    c = _centre(model)
    ijk = np.rint((c - model.grid.origin_mm) / model.spacing_mm).astype(int)
    pose = plane_pose(c + (0.3, 0.2, 4.0), (0.2, 0.1, -1.0))
    # the stroke on the block in place (one body)
    publish_split_box(state, 0, ijk - 12, ijk + 12, 0.0)
    start = state.tissue.count
    publish_cut(state, model.injury, pose, 5.0, 4.0, 3.0, 1.0)
    in_place, _ = _removed(state, start)
    assert len(in_place) > 100 and {k[0] for k in in_place} == {1}
    # again, the block moved (and turned) away: the stroke carried with it
    reset_state(model, state, rings=False)
    publish_split_box(state, 0, ijk - 12, ijk + 12, 0.0)
    move = np.array([30.0, -5.0, 2.0, np.cos(0.3), 0.0, 0.0, np.sin(0.3)])
    publish_pose(state, 1, move, 0.0)
    m = pose_matrix(move)
    moved_pose = np.concatenate([m[:, :3] @ pose[:3] + m[:, 3], _qmul(move[3:], pose[3:])])
    start = state.tissue.count
    publish_cut(state, model.injury, moved_pose, 5.0, 4.0, 3.0, 1.0)
    moved, _ = _removed(state, start)
    # the same voxels up to rounding at the rays' ends (the stroke was
    # carried in floating point): all of body 1, nearly all the same
    assert {k[0] for k in moved} == {1}
    common = len(set(moved) & set(in_place))
    assert common >= 0.99 * len(in_place) and abs(len(moved) - len(in_place)) <= \
        0.01 * len(in_place)
    # and the stroke where the block used to be cuts the bone left behind only
    start = state.tissue.count
    publish_cut(state, model.injury, pose, 5.0, 4.0, 3.0, 2.0)
    left, _ = _removed(state, start)
    assert all(k[0] == 0 for k in left)


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def test_an_axis_aligned_stroke_cuts_a_clean_box(model, state):
    """A stroke straight down an axis removes the box of voxels under it:
    rays every half voxel from a plane in mid-voxel, ``depth`` through the
    centres of whole voxels."""
    reset_state(model, state, rings=False)
    g = model.grid
    c = _centre(model) + 0.1 * g.spacing_mm      # off the voxel boundaries
    start = state.tissue.count
    n = publish_cut(state, model.injury, plane_pose(c, (0, 0, -1), (1, 0, 0)), 4.0, 3.0,
                    2.0, 0.0)
    got, _ = _removed(state, start)
    ijk = np.array([k[1:] for k in got])
    span = ijk.max(0) - ijk.min(0) + 1
    # 4 mm x 3 mm x 2 mm at 0.5 mm voxels: 8 or 9 voxels wide (the plane's
    # edge inside a voxel), 6 or 7 high, 4 or 5 deep
    assert span[0] in (8, 9) and span[1] in (6, 7) and span[2] in (4, 5)
    assert n == len(got) and n <= span.prod()


def test_strokes_are_deterministic_and_a_replica_follows(model):
    a, b = make_state(model), make_state(model)
    c = _centre(model)
    for st in (a, b):
        for k in range(3):          # a box cut: three strokes
            publish_cut(st, model.injury, plane_pose(c + (k * 2.0, 0, 3), (0.1, 0.2 * k, -1)),
                        6.0, 6.0, 4.0, 0.5 * k)
    ea, eb = a.tissue.read(0), b.tissue.read(0)
    for f in events.TISSUE_FIELDS:
        np.testing.assert_array_equal(ea[f], eb[f])
    np.testing.assert_array_equal(a.grid.density, b.grid.density)
    rep = TissueReplica(model)
    rep.apply(ea)
    np.testing.assert_array_equal(rep.grid.density == 0, a.grid.density == 0)
    np.testing.assert_array_equal(rep.state.removed_by_label, a.removed_by_label)


def test_bad_strokes_are_refused(model):
    st = make_state(model)
    with pytest.raises(ValueError, match="depth_mm"):
        publish_cut(st, model.injury, plane_pose((0, 0, 0), (0, 0, 1)), 1.0, 1.0, -1.0, 0.0)
    with pytest.raises(ValueError, match="not unit"):
        publish_cut(st, model.injury, (0, 0, 0, 2, 0, 0, 0), 1.0, 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="parallel"):
        plane_pose((0, 0, 0), (0, 0, 1), (0, 0, 2))
    assert st.tissue.count == 0


def test_plane_pose_axes():
    p = plane_pose((1, 2, 3), (0, 0, -2), (1, 0, 0))
    ax = plane_axes(p)
    np.testing.assert_allclose(ax[0], (1, 0, 0), atol=1e-12)
    np.testing.assert_allclose(ax[2], (0, 0, -1), atol=1e-12)
    np.testing.assert_allclose(ax @ ax.T, np.eye(3), atol=1e-12)


@settings(max_examples=15, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(off=offset, q=quat, rays=hs.sampled_from([1, 3, 17, 400]), moved=hs.booleans())
def test_a_stroke_in_slices_removes_what_the_stroke_at_once_removes(model, off, q, rays,
                                                                    moved):
    """queue_cut + one advance_cuts per step: the same removals in the same
    order, the same injuries (each after its body's last ray), the same
    tissue; the CUT record first, with n = -(rays per step)."""
    from bonesim.engine.cut_plane import advance_cuts, queue_cut

    once, sliced = make_state(model), make_state(model)
    c = _centre(model)
    for st in (once, sliced):
        if moved:                    # a second body, moved: both are cut in their frames
            publish_split_box(st, 0, (0, 0, 0), (60, 104, 104), 0.0)
            publish_pose(st, 1, (0.5, -0.3, 0.2, *pose_matrix_q(0.2)), 0.0)
    pose = _random_pose(c, [*off, *q])
    um = quantize_size(8.0, 6.0, 5.0)
    h0 = once.tissue.count
    n_once = publish_cut(once, model.injury, pose, 8.0, 6.0, 5.0, 1.0)
    queue_cut(sliced, model.injury, um, pose, 1.0, rays)
    n_sliced, k = 0, 0
    while sliced.cut_jobs:
        k += 1
        n_sliced += advance_cuts(sliced, 1.0 + k)
    assert n_sliced == n_once
    h = model.spacing_mm
    n_rays = len(sample_offsets(8.0, h)) * len(sample_offsets(6.0, h))
    assert k >= -(-n_rays // rays)
    a, b = once.tissue.read(h0), sliced.tissue.read(h0)
    assert b["kind"][0] == events.CUT and b["n"][0] == -rays and a["kind"][-1] == events.CUT
    assert a["n"][-1] == n_once
    np.testing.assert_array_equal(a["ijk"][-1], b["ijk"][0])
    np.testing.assert_array_equal(a["value"][-1], b["value"][0])
    for f in ("kind", "body", "label", "ijk", "n", "value"):
        np.testing.assert_array_equal(a[f][:-1], b[f][1:], err_msg=f)
    np.testing.assert_array_equal(once.grid.density, sliced.grid.density)
    np.testing.assert_array_equal(once.removed_by_label, sliced.removed_by_label)
    # each step's removals come from at most `rays` rays: no more than rays x the longest ray
    rem = b["kind"] == events.REMOVED
    if rem.any():
        _, per_step = np.unique(b["t_s"][rem], return_counts=True)
        assert per_step.max() <= rays * (int(np.ceil(np.sqrt(3) * 5.0 / model.spacing_mm)) + 2)


def pose_matrix_q(angle):
    """A unit quaternion (w, x, y, z) of ``angle`` [rad] about z."""
    return (float(np.cos(angle / 2)), 0.0, 0.0, float(np.sin(angle / 2)))


def test_a_large_stroke_through_the_world_step_is_sliced_and_one_behind_it_waits(model):
    from bonesim.engine.cut_plane import rays_per_step, stroke_rays
    from bonesim.engine.model import Sample
    from bonesim.engine.world import world_step
    from bonesim.engine.world_commands import CutStroke, Reset

    st = make_state(model)
    c = _centre(model)
    um = quantize_size(20.0, 20.0, 5.0)
    per = rays_per_step(5.0, model.spacing_mm)
    assert stroke_rays(um, model.spacing_mm) > per
    small = quantize_size(1.0, 1.0, 1.0)
    assert stroke_rays(small, model.spacing_mm) <= per
    away = Sample(0.0, c + 200.0, np.array([0.0, 0.0, -1.0]), False, 0.0, 1)
    pose = plane_pose(c + (0, 0, 3), (0, 0, -1))
    world_step(model, st, away, (CutStroke(pose, um), CutStroke(pose, small)))
    assert len(st.cut_jobs) == 2          # the small one waits behind the large one
    ev = st.tissue.read(0)
    assert (ev["kind"][:2] == events.CUT).all()
    assert ev["n"].tolist()[:2] == [-per, -rays_per_step(1.0, model.spacing_mm)]
    q = 1
    while st.cut_jobs:
        world_step(model, st, away._replace(t_s=q * 1e-3))
        q += 1
    assert q > 2
    # at once when nothing is under way; a reset drops a stroke under way
    h = st.tissue.count
    world_step(model, st, away._replace(t_s=1.0), (CutStroke(pose, small),))
    assert not st.cut_jobs and st.tissue.read(h)["kind"][-1] == events.CUT
    world_step(model, st, away._replace(t_s=1.1), (CutStroke(pose, um), Reset()))
    assert not st.cut_jobs
