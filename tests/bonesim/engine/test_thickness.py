"""Bone thickness under the burr: analytic plates and a numpy reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy import ndimage

from bonesim.engine.grid import Grid
from bonesim.engine.thickness import (BISECT_ITERS, MIN_GRADIENT, NO_CONTACT, STEP_FRACTION,
                                      bone_thickness_mm, contact_thickness)


def plate(thickness_mm, normal=(0.0, 0.0, 1.0), spacing=0.5, n=48, centre=None):
    """A plate of the given thickness through ``centre``, voxelized by centre
    inclusion; returns the grid, the unit normal and the centre."""
    nrm = np.asarray(normal, float) / np.linalg.norm(normal)
    c0 = np.full(3, (n - 1) * spacing / 2) if centre is None else np.asarray(centre, float)
    pts = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1) * spacing
    s = (pts - c0) @ nrm
    labels = ((s >= -thickness_mm / 2) & (s < thickness_mm / 2)).astype(np.uint8)
    return Grid.from_dense(labels, spacing_mm=spacing), nrm, c0


def touch(nrm, c0, thickness_mm, radius, depth=0.2):
    """Burr centre pressing ``depth`` into the plate's +normal face."""
    return c0 + nrm * (thickness_mm / 2 + radius - depth)


@pytest.mark.parametrize("thickness", [2.0, 0.8])
@pytest.mark.parametrize("spacing", [0.5, 0.25])
@pytest.mark.parametrize("radius", [0.5, 2.5])
def test_axis_aligned_plate(thickness, spacing, radius):
    g, nrm, c0 = plate(thickness, spacing=spacing)
    got = bone_thickness_mm(g, touch(nrm, c0, thickness, radius), radius)
    assert abs(got - thickness) <= spacing
    # the voxelized plate holds a whole number of voxels: the chord is exact
    voxels = round(thickness / spacing) if thickness / spacing % 1 == 0 else None
    if voxels is not None:
        assert got == pytest.approx(voxels * spacing, abs=1e-9)


@pytest.mark.parametrize("normal", [(1, 0, 2), (1, 1, 1), (0.3, 0.2, 1), (-2, 1, 0.5)])
@pytest.mark.parametrize("thickness", [2.0, 0.8])
def test_oblique_plate(normal, thickness):
    spacing = 0.25
    g, nrm, c0 = plate(thickness, normal, spacing=spacing, n=60)
    radius = 2.0
    ijk, normals, chords = contact_thickness(g, touch(nrm, c0, thickness, radius), radius)
    assert len(chords) >= 5
    # inward normals point into the plate, i.e. against the touched face's normal
    angle = np.degrees(np.arccos(np.clip(normals @ -nrm, -1, 1)))
    # (voxels at the staircase steps of a shallow tilt lean up to ~35 degrees)
    assert angle.mean() < 15.0 and angle.max() < 40.0
    mean = bone_thickness_mm(g, touch(nrm, c0, thickness, radius), radius)
    assert abs(mean - thickness) <= spacing


def test_touched_from_the_other_side_and_thinning():
    g, nrm, c0 = plate(2.0, spacing=0.5)
    assert bone_thickness_mm(g, touch(-nrm, c0, 2.0, 1.5), 1.5) == pytest.approx(2.0)
    # drill the plate down layer by layer from the top: thickness follows
    top = int(np.argmax(g.to_dense()[1][0, 0, ::-1] > 0))
    nz = g.shape[2] - 1 - top           # index of the top layer
    last = 2.0
    for layer in range(3):
        k = nz - layer
        for b in range(g.n_bricks):
            bi, bj, bk = g.bricks[b]
            lk = k - bk * 8
            if 0 <= lk < 8:
                g.density[b].reshape(8, 8, 8)[:, :, lk] = 0.0
        c = c0.copy()
        c[2] = (k - 0.5) * 0.5 + 1.5 - 0.2       # press 0.2 mm into the new top
        got = bone_thickness_mm(g, c, 1.5)
        if layer < 2:
            assert got == pytest.approx(last - 0.5)
        else:
            # one voxel left: no gradient across it; rays follow the burr's
            # radial direction, so off-centre chords are a little longer
            assert 0.5 <= got < 0.5 + 0.5 / 2
        last = got


def test_partial_density_is_bone_and_cap_and_no_contact():
    labels = np.zeros((30, 30, 30), np.uint8)
    labels[:, :, :25] = 1
    dens = np.ones(labels.shape, np.float32)
    dens[:, :, 24] = 0.3                       # a partly drilled top layer
    g = Grid.from_dense(labels, dens, spacing_mm=0.5)
    top = 24 * 0.5 + 0.25
    c = np.array([7.0, 7.0, top + 1.0 - 0.2])
    assert bone_thickness_mm(g, c, 1.0, max_mm=20.0) == pytest.approx(12.5)
    assert bone_thickness_mm(g, c, 1.0) == pytest.approx(10.0)     # default cap
    assert bone_thickness_mm(g, c, 1.0, max_mm=4.0) == pytest.approx(4.0)
    # well above the surface: nothing contacted
    assert bone_thickness_mm(g, c + [0, 0, 3.0], 1.0) == NO_CONTACT == math.inf
    ijk, normals, chords = contact_thickness(g, c + [0, 0, 3.0], 1.0)
    assert ijk.shape == (0, 3) and chords.shape == (0,)


def test_sliver_uses_direction_from_the_burr():
    labels = np.zeros((20, 20, 20), np.uint8)
    labels[:, :, 10] = 1                       # one voxel thick: no gradient across it
    g = Grid.from_dense(labels, spacing_mm=0.5)
    c = np.array([5.0, 5.0, 5.0 + 0.25 + 1.0 - 0.1])
    ijk, normals, chords = contact_thickness(g, c, 1.0)
    assert len(chords) == 1 and np.allclose(normals[0], [0, 0, -1])
    assert chords[0] == pytest.approx(0.5)


def test_bad_inputs():
    g, nrm, c0 = plate(1.0)
    with pytest.raises(ValueError):
        bone_thickness_mm(g, (0.0, np.nan, 0.0), 1.0)
    with pytest.raises(ValueError):
        bone_thickness_mm(g, (0.0, 0.0), 1.0)
    with pytest.raises(ValueError):
        bone_thickness_mm(g, c0, -1.0)
    with pytest.raises(ValueError):
        bone_thickness_mm(g, c0, 1.0, max_mm=0.0)


# ------------------------------------------------------------------ reference
def reference(dens, spacing, origin, centre, radius, max_mm):
    """Plain numpy version on a dense volume (outside counts as empty).

    Returns a dict ``(i, j, k) -> (normal, chord)``.
    """
    d = dens.astype(np.float64)
    occ = d > 0
    padded = np.pad(occ, 1)
    any_empty = np.zeros_like(occ)
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            for c in (-1, 0, 1):
                sl = padded[1 + a:1 + a + occ.shape[0], 1 + b:1 + b + occ.shape[1],
                            1 + c:1 + c + occ.shape[2]]
                any_empty |= ~sl
    grad = np.stack([ndimage.sobel(d, axis=ax, mode="constant", cval=0.0)
                     for ax in range(3)], -1)
    idx = np.argwhere(occ & any_empty)
    pos = origin + spacing * idx
    near = np.sum((pos - centre) ** 2, axis=1) <= (radius + 0.5 * spacing) ** 2
    idx, pos, grad = idx[near], pos[near], grad[tuple(idx[near].T)]
    g = np.linalg.norm(grad, axis=1)
    off = pos - centre
    r = np.linalg.norm(off, axis=1)
    normal = np.where((g > MIN_GRADIENT)[:, None], grad / np.maximum(g, 1e-300)[:, None],
                      off / np.maximum(r, 1e-300)[:, None])

    def bone(pts):
        ijk = np.floor((pts - origin) * (1.0 / spacing) + 0.5).astype(int)
        ok = np.all((ijk >= 0) & (ijk < np.array(occ.shape)), axis=1)
        out = np.zeros(len(pts), bool)
        out[ok] = occ[tuple(ijk[ok].T)]
        return out

    def exit_distance(direction):
        step = STEP_FRACTION * spacing
        res = np.full(len(pos), max_mm)
        done = np.zeros(len(pos), bool)
        s = step
        lo = np.zeros(len(pos))
        while s < max_mm and not done.all():
            out = ~bone(pos + s * direction) & ~done
            if out.any():
                a, b = lo[out].copy(), np.full(out.sum(), s)
                for _ in range(BISECT_ITERS):
                    mid = 0.5 * (a + b)
                    ins = bone(pos[out] + mid[:, None] * direction[out])
                    a = np.where(ins, mid, a)
                    b = np.where(ins, b, mid)
                res[out] = 0.5 * (a + b)
                done |= out
            lo[~done] = s
            s += step
        return res

    chord = np.minimum(exit_distance(normal) + exit_distance(-normal), max_mm)
    return {tuple(map(int, ijk)): (n, c) for ijk, n, c in zip(idx, normal, chord)}


@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2 ** 31 - 1), radius=hs.floats(0.3, 2.5),
       spacing=hs.sampled_from([0.5, 0.3]), max_mm=hs.sampled_from([10.0, 1.2]))
def test_matches_numpy_reference(seed, radius, spacing, max_mm):
    rng = np.random.default_rng(seed)
    shape = (14, 13, 12)
    blob = ndimage.gaussian_filter(rng.random(shape), 1.5)
    labels = (blob > np.median(blob)).astype(np.uint8)
    dens = np.where(rng.random(shape) < 0.2, rng.uniform(0.05, 1.0, shape), 1.0)
    dens = (dens * labels).astype(np.float32)
    origin = np.array([-1.0, 2.0, 0.5])
    g = Grid.from_dense(labels, dens, spacing_mm=spacing, origin_mm=origin)
    centre = origin + rng.uniform(0, 1, 3) * (np.array(shape) - 1) * spacing
    ref = reference(dens, spacing, origin, centre, radius, max_mm)
    ijk, normals, chords = contact_thickness(g, centre, radius, max_mm)
    got = {tuple(map(int, v)): (n, c) for v, n, c in zip(ijk, normals, chords)}
    assert got.keys() == ref.keys()
    for key, (n, c) in got.items():
        assert np.allclose(n, ref[key][0], atol=1e-9)
        assert c == pytest.approx(ref[key][1], abs=1e-9)
    mean = bone_thickness_mm(g, centre, radius, max_mm)
    if got:
        assert mean == pytest.approx(np.mean([c for _, c in ref.values()]))
    else:
        assert mean == NO_CONTACT


def test_exit_ray_with_bone_labels():
    """The labelled ray stops where the bone ends and says what it meets: a
    structure (its label), empty space (0) or nothing within reach (0)."""
    from bonesim.engine.thickness import exit_ray

    lab = np.zeros((8, 8, 16), np.uint8)
    lab[:, :, :4] = 2                          # a structure under
    lab[:, :, 4:9] = 1                         # 5 voxels of bone
    g = Grid.from_dense(lab, spacing_mm=0.5)
    bone = np.array([0, 1, 0], np.uint8)
    step = STEP_FRACTION * 0.5
    p = g.origin_mm + 0.5 * np.array([4, 4, 8])          # top bone voxel
    args = (g.keys, g.vals, g.density, g.label, bone)
    d, met = exit_ray(*args, True, g.origin_mm, 2.0, *p, 0.0, 0.0, -1.0, step, 10.0)
    assert met == 2 and d == pytest.approx(4.5 * 0.5, abs=step / 2 ** BISECT_ITERS)
    d, met = exit_ray(*args, True, g.origin_mm, 2.0, *p, 0.0, 0.0, 1.0, step, 10.0)
    assert met == 0 and d == pytest.approx(0.25, abs=step / 2 ** BISECT_ITERS)
    d, met = exit_ray(*args, True, g.origin_mm, 2.0, *p, 0.0, 0.0, 1.0, step, 10.0, True)
    assert (d, met) == (10.0, 0)                  # into empty space: no distance needed
    d, met = exit_ray(*args, True, g.origin_mm, 2.0, *p, 0.0, 0.0, -1.0, step, 1.0)
    assert (d, met) == (1.0, 0)                   # the structure is out of reach
    # without labels the structure is tissue too: the ray runs to the bottom
    d, met = exit_ray(*args, False, g.origin_mm, 2.0, *p, 0.0, 0.0, -1.0, step, 10.0)
    assert met == 0 and d == pytest.approx(8.5 * 0.5, abs=step / 2 ** BISECT_ITERS)


# ----------------------------------------------------------------- bodies
# the fakes' block, 4 mm thick here (top face z = 3.75 mm), split at x = 10 mm
_FILL = 8


def _split_block(pose=None, both=False):
    """The block split at x = 10 mm; body 1 (x >= 10 mm) placed at ``pose``
    (and body 0 too with ``both``)."""
    from bonesim.engine.bodies import publish_split_box, set_pose
    from tests.bonesim.fakes import block_model

    m, st = block_model(fill_z=_FILL)
    dst, n = publish_split_box(st, 0, (20, 0, 0), (39, 39, 39), 0.0)
    assert dst == 1 and n > 0
    if pose is not None:
        set_pose(st, 1, pose)
        if both:
            set_pose(st, 0, pose)
    return m, st


def _one():
    from tests.bonesim.fakes import block_model

    return block_model(fill_z=_FILL)[1]


# a quarter turn about x, then a lift out of body 0's reach
_POSE = (1.0, 30.0, 25.0, math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)


def _place(pose, p):
    from bonesim.engine.bodies import pose_matrix, to_case_frame

    return to_case_frame(pose_matrix(pose), p)


def test_one_body_at_the_identity_reads_as_before():
    from bonesim.engine.bodies import Bodies

    st = _one()
    _, two = _split_block()                     # two bodies, both at the identity
    for c in ([15.0, 10.0, 5.0], [10.2, 9.7, 4.6], [3.0, 3.0, 6.5]):
        ref = bone_thickness_mm(st.grid, c, 1.5)
        assert bone_thickness_mm(st.grid, c, 1.5, bodies=Bodies.of(st)) == ref
        assert bone_thickness_mm(two.grid, c, 1.5, bodies=two) == ref
        a, b = contact_thickness(st.grid, c, 1.5), contact_thickness(two.grid, c, 1.5,
                                                                    bodies=two)
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("c", [[15.0, 10.0, 5.0], [16.0, 2.0, 4.7]])
def test_thickness_over_a_moved_body_is_that_of_the_unmoved_block(c):
    one = _one()
    ref = bone_thickness_mm(one.grid, c, 1.5)
    assert 1.0 < ref < 10.0
    _, st = _split_block(_POSE)
    got = bone_thickness_mm(st.grid, _place(_POSE, c), 1.5, bodies=st)
    assert got == pytest.approx(ref, abs=1e-9)
    # where body 1 was cut, its voxels still lie in the grid: they are not read
    assert bone_thickness_mm(st.grid, c, 1.5, bodies=st) == NO_CONTACT
    assert bone_thickness_mm(st.grid, c, 1.5) == ref        # (ignoring bodies would)
    # normals come back in the case frame: the moved top face's inward normal
    _, nrm, _ = contact_thickness(st.grid, _place(_POSE, c), 1.5, bodies=st)
    _, nrm0, _ = contact_thickness(one.grid, c, 1.5)
    rot = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])      # the quarter turn
    np.testing.assert_allclose(nrm, nrm0 @ rot.T, atol=1e-12)


def test_bodies_at_one_pose_are_read_together_and_the_minimum_is_taken():
    one = _one()
    c = np.array([10.1, 10.0, 5.0])                 # straddles the split
    ref = bone_thickness_mm(one.grid, c, 1.5)
    _, st = _split_block(_POSE, both=True)
    assert bone_thickness_mm(st.grid, _place(_POSE, c), 1.5, bodies=st) == \
        pytest.approx(ref, abs=1e-9)
    # body 1 sunk by 1 mm beside body 0: the burr touches both; each is read
    # in its own frame and the thinner reading wins
    down = (0.0, 0.0, -1.0, 1.0, 0.0, 0.0, 0.0)
    c0 = np.array([10.0, 10.0, 4.2])
    _, st = _split_block(down)
    got = bone_thickness_mm(st.grid, c0, 1.5, bodies=st)
    _, only0 = _split_block((0.0, 0.0, -50.0, 1.0, 0.0, 0.0, 0.0))
    _, only1 = _split_block(down)
    from bonesim.engine.bodies import set_pose

    set_pose(only1, 0, (0.0, 0.0, -50.0, 1.0, 0.0, 0.0, 0.0))
    a = bone_thickness_mm(st.grid, c0, 1.5, bodies=only0)
    b = bone_thickness_mm(st.grid, c0, 1.5, bodies=only1)
    assert math.isfinite(a) and math.isfinite(b) and a != b
    assert got == min(a, b)
    # body 1 alone, sunk, reads as body 1 alone unmoved with the burr raised 1 mm
    _, ref1 = _split_block()
    set_pose(ref1, 0, (0.0, 0.0, -50.0, 1.0, 0.0, 0.0, 0.0))
    assert b == pytest.approx(bone_thickness_mm(ref1.grid, c0 + [0, 0, 1.0], 1.5,
                                                bodies=ref1), abs=1e-9)
