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
