"""Thinned dust sprites (bonesim.render.dustview, where the level of detail
is on): the cells kept against a plain evaluation of the hash, the same
every frame, about one in k; kept sprites drawn sqrt(k) times as wide."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from vtkmodules.util import numpy_support
from vtkmodules.vtkRenderingCore import vtkRenderer

from bonesim.render.dustview import DustLayer, sprite_look, thin_sprites
from bonesim.render.style import default_style


def _ref_keep(p, k):
    """Plain integers: the hash of the position's float32 bits."""
    m = 0xFFFFFFFF
    out = []
    for x, y, z in p:
        u = [struct.unpack("<I", struct.pack("<f", float(c)))[0] for c in (x, y, z)]
        h = (u[0] * 0x9E3779B1 + u[1] * 0x85EBCA77 + u[2] * 0xC2B2AE3D) & m
        h ^= h >> 15
        h = (h * 0x2C1B3C6D) & m
        h ^= h >> 12
        out.append(h % k == 0)
    return np.array(out)


def _positions(n, seed=0):
    rng = np.random.default_rng(seed)
    cells = rng.integers(-200, 200, size=(n, 3))
    return (0.19 * cells + rng.uniform(-0.05, 0.05, (n, 3))).astype(np.float32)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_thinning_matches_the_hash_and_keeps_about_one_in_k(k):
    p = _positions(3000)
    keep = thin_sprites(p, k)
    np.testing.assert_array_equal(keep, _ref_keep(p, k))
    np.testing.assert_array_equal(thin_sprites(p.copy(), k), keep)      # every frame
    assert abs(keep.mean() - 1.0 / k) < 0.04
    # a cell's choice does not depend on the others drawn with it
    np.testing.assert_array_equal(thin_sprites(p[::7], k), keep[::7])
    with pytest.raises(ValueError):
        thin_sprites(p, 0)


def test_layer_draws_the_kept_sprites_wider():
    st = default_style().dust
    layer = DustLayer(vtkRenderer(), st)
    p = _positions(2000, seed=3)
    d = np.random.default_rng(4).uniform(0.05, 1.0, len(p)).astype(np.float32)
    layer.set(p, d, 0.19)
    assert layer.count == len(p)
    layer.keep_one_in = 2
    layer.set(p, d, 0.19)
    keep = _ref_keep(p, 2)
    assert layer.count == keep.sum()
    pd = layer.polydata
    got_p = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
    np.testing.assert_array_equal(got_p, p[keep])
    r = numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("radius"))
    rgba = numpy_support.vtk_to_numpy(pd.GetPointData().GetScalars())
    want_r, want_c = sprite_look(d[keep], None, None, 0.19, st)
    np.testing.assert_allclose(r, want_r * np.sqrt(2), rtol=1e-6)
    np.testing.assert_array_equal(rgba, want_c)
