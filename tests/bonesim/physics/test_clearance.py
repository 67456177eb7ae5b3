"""Distances to structures at the label map's own resolution (bonesim.physics.clearance):
against brute force over every voxel's box, analytic cases, invariants."""
from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from bonesim.physics.clearance import LEAF_SIZE, Clearance


def brute(points, labels, spacing, origin, group):
    """Reference: the smallest distance from each point to the box of any
    voxel whose label is in ``group`` (every voxel, not only the surface)."""
    spacing = np.broadcast_to(np.asarray(spacing, float), (3,))
    centres = np.asarray(origin, float) + spacing * np.argwhere(np.isin(labels, list(group)))
    out = np.full(len(points), np.inf)
    for a in range(0, len(points), 64):
        gap = np.abs(points[a:a + 64, None, :] - centres[None]) - spacing / 2
        d = np.sqrt((np.maximum(gap, 0.0) ** 2).sum(-1))
        if d.shape[1]:
            out[a:a + 64] = d.min(1)
    return out


def random_map(rng, shape, n_labels, fill=0.15, blobs=4):
    """Random structures: a few boxes and scattered single voxels."""
    lab = np.zeros(shape, np.uint8)
    for _ in range(blobs):
        lo = rng.integers(0, shape)
        hi = lo + rng.integers(1, np.maximum(np.array(shape) // 2, 2))
        lab[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = rng.integers(1, n_labels + 1)
    speck = rng.random(shape) < fill * 0.1
    lab[speck] = rng.integers(1, n_labels + 1, speck.sum())
    return lab


def points_around(rng, shape, spacing, origin, n, pad=3.0):
    lo = np.asarray(origin) - pad
    hi = np.asarray(origin) + np.asarray(spacing) * np.array(shape) + pad
    p = lo + rng.random((n, 3)) * (hi - lo)
    # and voxel centres, faces and corners (ties between boxes)
    ijk = rng.integers(0, shape, (n // 4, 3))
    c = np.asarray(origin) + np.asarray(spacing) * ijk
    half = np.asarray(spacing) / 2
    faces = c + half * rng.integers(-1, 2, (n // 4, 3))
    return np.concatenate([p, c, faces])


# ------------------------------------------------------------ brute force
@pytest.mark.parametrize("seed", range(6))
def test_matches_brute_force_over_every_voxel(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(6, 28, 3))
    spacing = rng.uniform(0.15, 1.2, 3)                  # anisotropic
    origin = rng.uniform(-20, 20, 3)
    lab = random_map(rng, shape, 4)
    held = [1, 2, 3, 4]
    cl = Clearance(lab, spacing, origin, held)
    pts = points_around(rng, shape, spacing, origin, 1200)
    groups = [[1], [2], [3], [4], [1, 3], [1, 2, 3, 4]]
    got = cl.distances(pts, groups)
    for g, group in enumerate(groups):
        ref = brute(pts, lab, spacing, origin, group)
        np.testing.assert_allclose(got[:, g], ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cl.distance(pts), got[:, -1], rtol=0, atol=0)


def test_many_surface_voxels_deep_trees():
    """Thousands of surface voxels per structure (many levels of the
    hierarchy): still exact, also far away."""
    rng = np.random.default_rng(7)
    shape = (60, 50, 40)
    spacing = (0.2, 0.25, 0.31)
    lab = np.zeros(shape, np.uint8)
    x, y, z = np.indices(shape)
    lab[(x - 30) ** 2 + (y - 25) ** 2 < 100] = 1                    # a rod
    lab[rng.random(shape) < 0.01] = 2                                # dust
    cl = Clearance(lab, spacing, (0, 0, 0), [1, 2])
    assert len(cl.surface_voxels(1)) > 40 * LEAF_SIZE
    pts = points_around(rng, shape, spacing, (0, 0, 0), 600, pad=25.0)
    for group in ([1], [2], [1, 2]):
        np.testing.assert_allclose(cl.distance(pts, group),
                                   brute(pts, lab, spacing, (0, 0, 0), group), atol=1e-9)


def test_surface_voxels_are_those_with_an_exposed_face():
    rng = np.random.default_rng(3)
    lab = random_map(rng, (12, 9, 7), 2, fill=0.5)
    cl = Clearance(lab, 1.0, (0, 0, 0), [1, 2])
    pad = np.pad(lab, 1, constant_values=0)
    for s in (1, 2):
        mine = pad[1:-1, 1:-1, 1:-1] == s
        exposed = np.zeros_like(mine)
        for axis in range(3):
            for shift in (-1, 1):
                nb = np.roll(pad, shift, axis=axis)[1:-1, 1:-1, 1:-1]
                exposed |= mine & (nb != s)
        want = {tuple(v) for v in np.argwhere(exposed)}
        got = {tuple(v) for v in cl.surface_voxels(s)}
        assert got == want


# ------------------------------------------------------------ analytic cases
def test_slab_is_exact_with_anisotropic_spacing():
    spacing = np.array([0.3, 0.45, 0.17])
    origin = np.array([-3.0, 1.0, 2.0])
    lab = np.zeros((20, 15, 40), np.uint8)
    lab[:, :, 12:19] = 5                                   # a slab across the volume
    cl = Clearance(lab, spacing, origin, [5])
    z_lo = origin[2] + spacing[2] * (12 - 0.5)
    z_hi = origin[2] + spacing[2] * (18 + 0.5)
    rng = np.random.default_rng(0)
    n = 500
    p = np.column_stack([origin[0] + rng.random(n) * 19 * spacing[0],
                         origin[1] + rng.random(n) * 14 * spacing[1],
                         rng.uniform(z_lo - 10, z_hi + 10, n)])
    want = np.maximum.reduce([z_lo - p[:, 2], p[:, 2] - z_hi, np.zeros(n)])
    np.testing.assert_allclose(cl.distance(p), want, rtol=0, atol=1e-12)


def test_single_voxel_box():
    lab = np.zeros((5, 5, 5), np.uint8)
    lab[2, 3, 1] = 1
    spacing = np.array([1.0, 2.0, 0.5])
    cl = Clearance(lab, spacing, (10.0, 0.0, 0.0), [1])
    centre = np.array([12.0, 6.0, 0.5])
    assert cl.distance(centre)[0] == 0.0
    # off a face, an edge and a corner of the 1 x 2 x 0.5 box
    assert cl.distance(centre + [0.5 + 2.0, 0, 0])[0] == pytest.approx(2.0)
    assert cl.distance(centre + [0.5 + 3.0, 1.0 + 4.0, 0])[0] == pytest.approx(5.0)
    assert cl.distance(centre + [0.5 + 1.0, 1.0 + 2.0, 0.25 + 2.0])[0] == pytest.approx(3.0)


def test_sphere_within_half_a_voxel_diagonal():
    h = np.array([0.2, 0.2, 0.35])
    n = (80, 80, 46)
    idx = np.indices(n).reshape(3, -1).T
    centre = h * (np.array(n) - 1) / 2
    radius = 5.0
    inside = np.linalg.norm(idx * h - centre, axis=1) <= radius
    lab = inside.reshape(n).astype(np.uint8)
    cl = Clearance(lab, h, (0, 0, 0), [1])
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    dist = rng.uniform(0.0, 15.0, 400)
    p = centre + dirs * (radius + dist)[:, None]
    half_diag = np.linalg.norm(h) / 2
    assert np.all(np.abs(cl.distance(p) - dist) <= half_diag + 1e-9)
    # inside the sphere: zero
    q = centre + dirs * (rng.random(400) * (radius - half_diag))[:, None]
    assert np.all(cl.distance(q) == 0.0)


# ------------------------------------------------------------ invariants
@st.composite
def maps_and_points(draw):
    shape = tuple(draw(st.lists(st.integers(1, 9), min_size=3, max_size=3)))
    lab = draw(hnp.arrays(np.uint8, shape, elements=st.sampled_from([0, 0, 0, 1, 2])))
    spacing = np.array(draw(st.lists(st.floats(0.05, 3.0), min_size=3, max_size=3)))
    origin = np.array(draw(st.lists(st.floats(-50, 50), min_size=3, max_size=3)))
    extent = spacing * np.array(shape)
    unit = draw(hnp.arrays(np.float64, (2, 3), elements=st.floats(-0.5, 1.5)))
    return lab, spacing, origin, origin - spacing / 2 + unit * extent


@settings(max_examples=150, deadline=None)
@given(case=maps_and_points(), group=st.sampled_from([[1], [2], [1, 2]]))
def test_lipschitz_zero_inside_and_brute_force(case, group):
    lab, spacing, origin, pts = case
    cl = Clearance(lab, spacing, origin, [1, 2])
    d = cl.distance(pts, group)
    ref = brute(pts, lab, spacing, origin, group)
    np.testing.assert_allclose(d, ref, rtol=0, atol=1e-9)
    # 1-Lipschitz between the two points
    if np.all(np.isfinite(d)):
        assert abs(d[0] - d[1]) <= np.linalg.norm(pts[0] - pts[1]) + 1e-9
    # zero at every voxel centre of the group, positive at the others' centres
    # when no voxel of the group touches them
    centres = origin + spacing * np.argwhere(np.ones(lab.shape, bool))
    dc = cl.distance(centres, group)
    member = np.isin(lab, group).ravel()
    assert np.all(dc[member] == 0.0)
    assert np.all(dc[~member] >= 0.0)
    far = brute(centres[~member], lab, spacing, origin, group) > 0
    assert np.all(dc[~member][far] > 0)


def test_union_is_the_minimum_and_empty_groups_are_inf():
    rng = np.random.default_rng(4)
    lab = random_map(rng, (15, 15, 15), 3)
    lab[lab == 3] = 0
    cl = Clearance(lab, 0.4, (1, 2, 3), [1, 2, 3])
    p = points_around(rng, lab.shape, np.full(3, 0.4), (1, 2, 3), 300)
    d = cl.distances(p, [[1], [2], [1, 2], [3]])
    np.testing.assert_array_equal(d[:, 2], np.minimum(d[:, 0], d[:, 1]))
    assert np.all(np.isinf(d[:, 3]))                      # structure 3 has no voxels
    assert np.isnan(cl.distance([np.nan, 0, 0])[0])


# ------------------------------------------------------------ the object
def test_pickles_small_and_answers_the_same():
    from bonesim.io.phantom import phantom_volume

    vol = phantom_volume(7, 0.25, (52.0, 52.0, 52.0))
    danger = list(range(2, 9))
    cl = Clearance(vol.labels, vol.spacing_mm, vol.origin_mm, danger)
    blob = pickle.dumps(cl)
    assert len(blob) < 4e6 and len(blob) < vol.labels.nbytes / 4     # never the volume
    back = pickle.loads(blob)
    rng = np.random.default_rng(0)
    p = vol.origin_mm + rng.random((2000, 3)) * 52.0
    np.testing.assert_array_equal(back.distances(p, [[5], danger]),
                                  cl.distances(p, [[5], danger]))
    with pytest.raises(ValueError):
        cl._node[0, 0] = 1                                # read-only arrays


def test_from_native_and_bad_input():
    from bonesim.io.volumes import NativeLabels

    lab = np.zeros((4, 4, 4), np.uint8)
    lab[1, 1, 1] = 2
    nat = NativeLabels(lab, (0.5, 0.6, 0.7), (1.0, 2.0, 3.0))
    cl = Clearance.from_native(nat, [2])
    assert cl.distance([1.5, 2.6, 3.7])[0] == 0.0
    assert cl.distance([1.5 + 0.25 + 1.0, 2.6, 3.7])[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="3-D uint8"):
        Clearance(lab.astype(np.int32), 1.0, (0, 0, 0), [2])
    with pytest.raises(ValueError, match="spacing_mm must be positive"):
        Clearance(lab, (1.0, 0.0, 1.0), (0, 0, 0), [2])
    with pytest.raises(ValueError, match="origin_mm must be finite"):
        Clearance(lab, 1.0, (0, math.inf, 0), [2])
    with pytest.raises(ValueError, match="1-255"):
        Clearance(lab, 1.0, (0, 0, 0), [0])
    with pytest.raises(ValueError, match="not held"):
        cl.distance([0, 0, 0], [3])
    with pytest.raises(ValueError, match="groups mask"):
        cl.distances([0, 0, 0], np.ones((1, 3), np.uint8))


# ------------------------------------------------------ the starting bound
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), step=st.sampled_from([0.0, 0.05, 0.7, 9.0]))
def test_a_batch_answers_each_point_as_if_asked_alone(seed, step):
    """Each search starts from the previous point's distance plus the step
    (the batch order matters for speed only): a path of points, with
    jumps, repeats, non-finite points and points inside, gives the bits of
    the same points asked one at a time (every search from infinity)."""
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(5, 16, 3))
    spacing = rng.uniform(0.2, 1.0, 3)
    origin = rng.uniform(-5, 5, 3)
    lab = random_map(rng, shape, 3)
    cl = Clearance(lab, spacing, origin, [1, 2, 3])
    walk = points_around(rng, shape, spacing, origin, 40)[:1] + np.cumsum(
        rng.normal(0.0, step + 1e-3, (60, 3)), axis=0)
    pts = np.concatenate([walk, points_around(rng, shape, spacing, origin, 40), walk[::-1]])
    pts[rng.integers(0, len(pts), 3)] = np.nan
    groups = [[1], [2, 3], [1, 2, 3]]
    got = cl.distances(pts, groups)
    alone = np.array([cl.distances(p, groups)[0] for p in pts])
    np.testing.assert_array_equal(got, alone)
    finite = np.all(np.isfinite(pts), axis=1)
    for g, group in enumerate(groups):
        np.testing.assert_allclose(got[finite, g], brute(pts[finite], lab, spacing, origin,
                                                         group), rtol=0, atol=1e-9)
