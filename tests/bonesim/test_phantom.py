"""The procedural left temporal-bone phantom (bonesim.phantom)."""
from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import ndimage

from bonesim import phantom as P

H = P.DEFAULT_VOXEL_MM


@pytest.fixture(scope="module")
def parts():
    return P.build_phantom(seed=3)


def centroid(mask, parts):
    return parts.origin_mm + H * np.argwhere(mask).mean(axis=0)


def test_deterministic_from_seed(parts):
    again = P.build_phantom(seed=3)
    for name in P.PARTS:
        np.testing.assert_array_equal(again.masks[name], parts.masks[name])
    np.testing.assert_array_equal(again.hu, parts.hu)
    other = P.build_phantom(seed=4)
    assert not np.array_equal(other.air_cells, parts.air_cells)
    # the named anatomy does not depend on the seed
    for name in P.PARTS[1:]:
        np.testing.assert_array_equal(other.masks[name], parts.masks[name])


def test_generation_is_fast():
    P.build_phantom(seed=0)                   # warm caches
    t0 = time.perf_counter()
    P.phantom_volume(seed=1)
    assert time.perf_counter() - t0 < 1.0


def test_every_structure_present_and_labels_follow_order():
    order = tuple(reversed(P.PARTS))
    vol = P.phantom_volume(seed=2, structures=order)
    counts = vol.counts(len(order))
    assert (counts[1:] > 0).all(), dict(zip(order, counts[1:]))
    assert vol.labels.dtype == np.uint8 and vol.hu.dtype == np.float32
    assert counts[order.index("bone") + 1] == counts[1:].max()
    with pytest.raises(ValueError, match="unknown phantom part"):
        P.phantom_volume(structures=("bone", "brain"))


def test_omitted_part_is_empty():
    vol = P.phantom_volume(seed=2, structures=("bone", "facial_nerve"))
    assert set(np.unique(vol.labels)) == {0, 1, 2}
    parts = P.build_phantom(seed=2)
    assert (vol.labels[parts.masks["labyrinth"]] == 0).all()
    assert (vol.hu[parts.masks["labyrinth"]] == P.HU_AIR).all()


def test_size_and_grid(parts):
    assert parts.hu.shape == (104, 104, 104)
    np.testing.assert_allclose(parts.origin_mm, -25.75)
    bone = np.argwhere(parts.masks["bone"])
    extent = (bone.max(0) - bone.min(0) + 1) * H
    assert (extent > 38).all() and (extent <= 52).all() and extent.max() > 44


def test_intensities(parts):
    hu = parts.hu
    bone = hu[parts.masks["bone"]]
    assert 1400 < bone.mean() < 1600 and bone.std() > 30 and bone.min() > 600
    assert (hu[parts.air_cells] == P.HU_AIR).all()
    for name in ("sigmoid_sinus", "middle_fossa_dura", "facial_nerve"):
        assert (hu[parts.masks[name]] < 100).all()
    assert (hu == np.rint(hu)).all()


def test_air_cells_keep_the_cortex(parts):
    cells = parts.air_cells
    assert 500 < cells.sum() * H ** 3 < 8000             # well pneumatized [mm^3]
    dist = ndimage.distance_transform_edt(parts.envelope, sampling=H)
    assert dist[cells].min() >= P.CORTEX_MM
    # the lateral surface is intact bone in every column that meets the block
    bone_or_soft = parts.masks["bone"] | cells
    cols = bone_or_soft.any(axis=0)
    outer = bone_or_soft.shape[0] - 1 - np.argmax(bone_or_soft[::-1], axis=0)
    assert not cells[outer[cols], *np.nonzero(cols)].any()


def test_left_ear_relations(parts):
    m = parts.masks
    bone = m["bone"]
    # lateral surface of the bone block (max x with bone per (y, z) column)
    def cortex_x(j, k):
        col = np.nonzero(bone[:, j, k] | parts.air_cells[:, j, k])[0]
        return parts.origin_mm[0] + H * col.max()

    facial = np.argwhere(m["facial_nerve"])
    z = parts.origin_mm[2] + H * facial[:, 2]
    mastoid_seg = facial[(z < -3) & (z > -14)]     # above the foramen's slope
    depth = [cortex_x(j, k) - (parts.origin_mm[0] + H * i) for i, j, k in mastoid_seg]
    assert 10.0 <= min(depth) and max(depth) <= 16.0

    sinus, fn = centroid(m["sigmoid_sinus"], parts), centroid(m["facial_nerve"], parts)
    lab = centroid(m["labyrinth"], parts)
    dura = centroid(m["middle_fossa_dura"], parts)
    assert sinus[1] > fn[1] + 8                           # sinus posterior
    assert lab[0] < fn[0]                                 # labyrinth medial to FN
    assert dura[2] > P.TEGMEN_Z_MM > P.ANTRUM_CENTER_MM[2]  # tegmen superior
    # the antrum is an air space anterior-superior in the mastoid
    a = np.rint((np.asarray(P.ANTRUM_CENTER_MM) - parts.origin_mm) / H).astype(int)
    assert not any(m[n][tuple(a)] for n in P.PARTS)
    cells = centroid(parts.air_cells, parts)
    assert P.ANTRUM_CENTER_MM[1] < cells[1] and P.ANTRUM_CENTER_MM[2] > cells[2]
    # chorda tympani leaves the facial nerve
    touching = ndimage.binary_dilation(m["chorda_tympani"]) & m["facial_nerve"]
    assert touching.any()
    # the camera of the bundled case looks from outside the bone, laterally
    assert np.argwhere(bone)[:, 0].max() * H + parts.origin_mm[0] < 25


def test_landmarks_are_where_documented(parts):
    lm = P.LANDMARKS_MM
    idx = lambda p: tuple(np.rint((np.asarray(p) - parts.origin_mm) / H).astype(int))
    assert parts.masks["facial_nerve"][idx(lm["facial_mastoid_mid"])]
    x, y, z = lm["mastoid_cortex"]
    assert parts.masks["bone"][idx((x - 1.0, y, z))]
    assert not parts.masks["bone"][idx((x + 1.0, y, z))]
    sx, sy, sz = lm["sigmoid_sinus_lateral"]
    assert parts.masks["sigmoid_sinus"][idx((sx - 1.0, sy, sz))]
    assert not parts.masks["sigmoid_sinus"][idx((sx + 1.0, sy, sz))]
