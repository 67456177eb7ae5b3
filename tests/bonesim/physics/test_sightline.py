"""depth_below_surface_mm: exact chords through occupied voxels, checked
against analytic slabs and a naive dense ray march."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as hs

from bonesim.engine.grid import Grid
from bonesim.physics.sightline import depth_below_surface_mm

H = 0.5


def slab_grid(k0, k1, shape=(24, 24, 24), origin=(0.0, 0.0, 0.0)):
    """Tissue in the voxel layers k0 <= k < k1 (z from (k0 - 1/2) h to (k1 - 1/2) h)."""
    lab = np.zeros(shape, np.uint8)
    lab[:, :, k0:k1] = 1
    return Grid.from_dense(lab, spacing_mm=H, origin_mm=origin)


def naive_depth(dense, origin, h, pos, eye, radius, n=20000):
    """Midpoint-rule march of the sight line over a dense density array."""
    pos, eye = np.asarray(pos, float), np.asarray(eye, float)
    v = eye - pos
    dist = np.linalg.norm(v)
    if dist <= radius:
        return 0.0
    u = v / dist
    length = dist - radius
    t = (np.arange(n) + 0.5) * (length / n)
    pts = pos + radius * u + t[:, None] * u
    ijk = np.floor((pts - origin) / h + 0.5).astype(int)
    ok = np.all((ijk >= 0) & (ijk < np.array(dense.shape)), axis=1)
    occ = np.zeros(n, bool)
    occ[ok] = dense[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]] > 0
    return float(occ.sum() * length / n)


def test_slab_straight_up_is_its_thickness():
    g = slab_grid(10, 16)                       # 6 layers: 3 mm
    pos = (6.0, 6.0, 2.0)                       # below the slab
    assert depth_below_surface_mm(g, pos, (6.0, 6.0, 40.0), 1.0) == pytest.approx(3.0,
                                                                                  abs=1e-9)


@pytest.mark.parametrize("theta_deg", [0.0, 20.0, 35.0, 50.0])
def test_slab_at_an_angle_is_thickness_over_cosine(theta_deg):
    g = slab_grid(10, 14, shape=(64, 64, 24))   # 4 layers: 2 mm
    th = math.radians(theta_deg)
    pos = np.array([10.0, 10.0, 1.0])
    phi = 0.3                                   # azimuth: not in an axis plane
    d = np.array([math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), math.cos(th)])
    eye = pos + 40.0 * d
    cos = d[2]
    got = depth_below_surface_mm(g, pos, eye, 0.5)
    assert got == pytest.approx(2.0 / cos, rel=1e-9)


def test_nothing_covers_the_burr():
    g = slab_grid(0, 6)                          # tissue below the burr only
    assert depth_below_surface_mm(g, (6.0, 6.0, 5.0), (6.0, 6.0, 60.0), 1.0) == 0.0


def test_burr_inside_bone_counts_from_its_surface():
    g = slab_grid(0, 20)                         # bone up to z = 9.75 mm
    # burr centre at z = 4, radius 1.5: surface at 5.5, bone above it 4.25 mm
    got = depth_below_surface_mm(g, (6.0, 6.0, 4.0), (6.0, 6.0, 80.0), 1.5)
    assert got == pytest.approx(9.75 - 5.5, abs=1e-9)


def test_eye_inside_the_burr_or_far_outside_the_grid():
    g = slab_grid(10, 16)
    assert depth_below_surface_mm(g, (6.0, 6.0, 2.0), (6.0, 6.0, 2.5), 1.0) == 0.0
    # the eye far away, the line leaving the grid sideways before the slab
    assert depth_below_surface_mm(g, (6.0, 6.0, 2.0), (-500.0, 6.0, 2.0), 1.0) == 0.0
    # the eye far above: same as a near one above the slab
    a = depth_below_surface_mm(g, (6.0, 6.0, 2.0), (6.0, 6.0, 1e4), 1.0)
    assert a == pytest.approx(3.0, abs=1e-9)


def test_removed_voxels_do_not_count():
    g = slab_grid(10, 16)
    # drill a hole up through the slab above the burr
    for k in range(10, 16):
        b = g.brick_index(12, 12, k)
        from bonesim.engine.grid import voxel_offset
        g.density[b, voxel_offset(12, 12, k)] = 0.0
    assert depth_below_surface_mm(g, (6.0, 6.0, 2.0), (6.0, 6.0, 40.0), 1.0) == 0.0


def test_bad_input():
    g = slab_grid(10, 16)
    with pytest.raises(ValueError, match="pos_mm"):
        depth_below_surface_mm(g, (np.nan, 0, 0), (0, 0, 9), 1.0)
    with pytest.raises(ValueError, match="eye_mm"):
        depth_below_surface_mm(g, (0, 0, 0), (0, 9), 1.0)
    with pytest.raises(ValueError, match="radius_mm"):
        depth_below_surface_mm(g, (0, 0, 0), (0, 0, 9), -1.0)


@settings(max_examples=60, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1),
       pos=hs.tuples(*[hs.floats(-2.0, 9.0)] * 3),
       eye=hs.tuples(*[hs.floats(-15.0, 25.0)] * 3),
       radius=hs.floats(0.0, 2.0))
@example(seed=0, pos=(0.0, 0.0, -2.220446049250313e-16), eye=(0.0, 1.0, 0.0), radius=0.0)
def test_matches_a_naive_dense_march(seed, pos, eye, radius):
    rng = np.random.default_rng(seed)
    shape = (14, 12, 16)
    origin = np.array([-1.0, 0.5, -0.25])
    # A segment that runs along a voxel face, within rounding of it, lies in
    # both voxels that share the face: either answer is right, and which one
    # each march takes depends on the last bit. Such segments are excluded
    # (the example above is one, kept to show it is skipped, not failed).
    for a in range(3):
        face = (pos[a] - origin[a]) / H + 0.5
        if abs(eye[a] - pos[a]) < 1e-6 and abs(face - round(face)) < 1e-6:
            assume(False)
    lab = (rng.random(shape) < 0.35).astype(np.uint8)
    g = Grid.from_dense(lab, spacing_mm=H, origin_mm=origin)
    dense, _ = g.to_dense(shape=shape)
    got = depth_below_surface_mm(g, pos, eye, radius)
    n = 40000
    ref = naive_depth(dense, origin, H, pos, eye, radius, n=n)
    length = max(np.linalg.norm(np.subtract(eye, pos)) - radius, 0.0)
    # each of the at most ~3 * shape boundary crossings may shift the
    # midpoint rule by one sample
    tol = 2 * sum(shape) * length / n + 1e-9
    assert got == pytest.approx(ref, abs=tol)
    assert 0.0 <= got <= length + 1e-9
