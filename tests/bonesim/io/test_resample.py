"""Slab-by-slab resampling (bonesim.io.resample) against scipy's whole-volume one."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.io import resample as R

SPACINGS = [0.1, 0.19, 0.25, 0.3, 0.5, 0.7, 1.0, 1.3]


@pytest.fixture
def tiny_slabs(monkeypatch):
    """Slabs of a few voxels, so every volume here is cut into many."""
    monkeypatch.setattr(R, "SLAB_VOXELS", 7)


def _scipy(data, spacing, voxel, order):
    sp = np.asarray(spacing, float)
    shape = tuple(int(n) for n in np.maximum(1, np.round(np.array(data.shape) * sp / voxel)))
    scale = voxel / sp
    return scipy.ndimage.affine_transform(data, scale, offset=0.5 * scale - 0.5,
                                          output_shape=shape, order=order, mode="nearest",
                                          prefilter=False)


def test_slabs_cover_every_plane_once():
    assert list(R.slabs(10, 3, budget=7)) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    assert list(R.slabs(3, 100, budget=7)) == [(0, 1), (1, 2), (2, 3)]   # one plane at least
    assert list(R.slabs(5, 4)) == [(0, 5)]
    assert list(R.slabs(0, 4)) == []


def test_label_counts_is_bincount(tiny_slabs):
    rng = np.random.default_rng(1)
    lab = rng.integers(0, 9, size=(6, 5, 4)).astype(np.uint8)
    np.testing.assert_array_equal(R.label_counts(lab, 12),
                                  np.bincount(lab.ravel(), minlength=12))
    np.testing.assert_array_equal(R.label_counts(lab), np.bincount(lab.ravel()))
    lab[0, 0, 0] = 200
    assert len(R.label_counts(lab, 3)) == 201 and R.label_counts(lab)[200] == 1
    assert R.label_counts(np.zeros((2, 2, 2), np.uint8), 4).tolist() == [8, 0, 0, 0]


@settings(max_examples=200, deadline=None)
@given(shape=st.tuples(*[st.integers(1, 9)] * 3),
       spacing=st.tuples(*[st.sampled_from(SPACINGS)] * 3),
       voxel=st.sampled_from([0.19, 0.2, 0.25, 0.5, 0.6]))
def test_nearest_in_slabs_matches_scipy(shape, spacing, voxel):
    data = (np.arange(np.prod(shape)) % 251).astype(np.uint8).reshape(shape)
    old = R.SLAB_VOXELS
    R.SLAB_VOXELS = 5                                 # (hypothesis: no fixtures)
    try:
        got, origin = R.resample_isotropic(data, spacing, (1.0, 2.0, 3.0), voxel, order=0)
    finally:
        R.SLAB_VOXELS = old
    if np.allclose(spacing, voxel):
        assert got is data
        return
    np.testing.assert_array_equal(got, _scipy(data, spacing, voxel, 0))
    assert got.flags.c_contiguous and got.dtype == np.uint8
    np.testing.assert_allclose(origin, np.array([1.0, 2.0, 3.0]) - np.array(spacing) / 2
                               + voxel / 2)


@settings(max_examples=100, deadline=None)
@given(shape=st.tuples(*[st.integers(1, 8)] * 3),
       spacing=st.tuples(*[st.sampled_from(SPACINGS)] * 3),
       voxel=st.sampled_from([0.19, 0.25, 0.5, 0.6]))
def test_linear_in_slabs_matches_scipy(shape, spacing, voxel):
    rng = np.random.default_rng(sum(shape))
    data = rng.normal(0, 500, size=shape).astype(np.float32)
    old = R.SLAB_VOXELS
    R.SLAB_VOXELS = 5
    try:
        got, _ = R.resample_isotropic(data, spacing, (0, 0, 0), voxel, order=1)
    finally:
        R.SLAB_VOXELS = old
    if np.allclose(spacing, voxel):
        assert got is data
        return
    want = _scipy(data.astype(np.float64), spacing, voxel, 1)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-2)


def test_linear_keeps_an_integer_type_rounded(tiny_slabs):
    ramp = np.broadcast_to(np.arange(5, dtype=np.int16)[:, None, None] * 11,
                           (5, 2, 3)).copy()
    got, _ = R.resample_isotropic(ramp, (1.0, 1.0, 1.0), (0, 0, 0), 0.5, order=1)
    assert got.dtype == np.int16
    want = _scipy(ramp.astype(np.float64), (1.0, 1.0, 1.0), 0.5, 1)
    np.testing.assert_array_equal(got, np.rint(want).astype(np.int16))
    # clipped to the type, not wrapped
    edge = np.full((2, 1, 1), 255, np.uint8)
    assert R.resample_isotropic(edge, (1.0, 1.0, 1.0), (0, 0, 0), 0.5, 1)[0].max() == 255


def test_an_axis_already_at_the_voxel_is_kept(tiny_slabs):
    """A 0.2 x 0.2 x 0.5 mm stack at 0.2 mm: x and y keep their voxels."""
    rng = np.random.default_rng(3)
    lab = rng.integers(0, 5, size=(4, 3, 2)).astype(np.uint8)
    got, origin = R.resample_isotropic(lab, (0.2, 0.2, 0.5), (0, 0, 0), 0.2, order=0)
    assert got.shape == (4, 3, 5)
    np.testing.assert_array_equal(got, _scipy(lab, (0.2, 0.2, 0.5), 0.2, 0))
    np.testing.assert_allclose(origin, [0, 0, -0.15])


def test_bad_order():
    with pytest.raises(ValueError, match="order"):
        R.resample_isotropic(np.zeros((2, 2, 2)), (1, 1, 1), (0, 0, 0), 0.5, order=3)
