"""The structures' drawn subset (bonesim.render.structure_subset): sealed
triangles against a plain loop over the definition, unsealing near removed
voxels never keeps a triangle a fresh evaluation would draw, and the
picture is the same pixel for pixel with and without the subset."""
from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util import numpy_support

from bonesim.engine.surface import Surface
from bonesim.render.scene import Scene
from bonesim.render.structure_subset import SEAL_RADIUS, SealedTriangles
from tests.bonesim.render.scenes import nerve_block


def _mesh(scene, name):
    pd = scene._structures[name].GetMapper().GetInput()
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
    sub = scene._sealed[name][0]
    return pts, sub


def _ref_sealed(grid0, grid, surf, pts, tris, r=SEAL_RADIUS):
    """Plain loops: the block of radius ``r`` (SEAL_RADIUS) around each
    triangle's voxel occupied in ``grid0`` and in ``grid``, and no vertex of
    ``surf`` within ``r + 1``."""
    out = np.zeros(len(tris), np.uint8)
    for t, tri in enumerate(tris):
        c = np.floor((pts[tri].astype(np.float64).mean(0) - grid.origin_mm)
                     / grid.spacing_mm + 0.5).astype(int)
        ok = all(grid0.density_at(*(c + d)) > 0 and grid.density_at(*(c + d)) > 0
                 for d in np.ndindex(2 * r + 1, 2 * r + 1, 2 * r + 1)
                 for d in [np.array(d) - r])
        if ok:
            q = r + 1
            ok = all(surf.vertex_at(*(c + np.array(d) - q)) < 0
                     for d in np.ndindex(2 * q + 1, 2 * q + 1, 2 * q + 1))
        out[t] = ok
    return out


def _drill(grid, i_range, j_range, k_from):
    """Empty the voxels of a box (bone column down to ``k_from``); returns them."""
    from bonesim.engine.grid import voxel_offset

    out = []
    for i in range(*i_range):
        for j in range(*j_range):
            for k in range(k_from, grid.shape[2]):
                b = grid.brick_index(i, j, k)
                if b >= 0 and grid.density[b, voxel_offset(i, j, k)] > 0:
                    grid.density[b, voxel_offset(i, j, k)] = 0.0
                    out.append((i, j, k))
    return np.array(out, np.int32).reshape(-1, 3)


@pytest.fixture
def nerve_scene(gl_info):
    model, state = nerve_block()
    surf = Surface.build(state.grid, model.colors)
    sc = Scene(size=(240, 180), panel=False, visible_subset=False)
    sc.update_surface(surf)
    sc.add_structures(model.grid, model.structures)
    yield model, state, surf, sc
    sc.close()


def test_sealed_triangles_match_the_definition(nerve_scene):
    model, state, surf, sc = nerve_scene
    pts, sub = _mesh(sc, "nerve")
    want = _ref_sealed(model.grid, state.grid, surf, pts, sub.tris)
    assert np.array_equal(sub.sealed, want)
    # the rod runs inside the block and out of its two faces: both kinds
    assert 0 < want.sum() < len(want)


def test_unsealing_near_removed_voxels_is_conservative(nerve_scene):
    model, state, surf, sc = nerve_scene
    pts, sub = _mesh(sc, "nerve")
    before = sub.sealed.copy()
    removed = _drill(state.grid, (12, 20), (12, 20), 10)      # down to just over the nerve
    surf.update(state.grid, removed)
    sc.update_surface(surf, removed)
    fresh = _ref_sealed(model.grid, state.grid, surf, pts, sub.tris)
    # never sealed where a fresh evaluation on the drilled tissue would draw it
    assert not np.any(sub.sealed.astype(bool) & ~fresh.astype(bool))
    assert np.any(before.astype(bool) & ~sub.sealed.astype(bool))     # something opened
    assert np.all(sub.sealed <= before)                               # nothing closed


def _view(sc):
    sc.render()
    return sc.image().copy()


def test_picture_is_the_same_with_and_without_the_subset(nerve_scene):
    model, state, surf, sc = nerve_scene
    removed = _drill(state.grid, (12, 20), (12, 20), 10)       # opens the nerve
    surf.update(state.grid, removed)
    sc.update_surface(surf, removed)
    sc.set_camera((8.0, 8.0, 30.0), (8.0, 7.9, 4.0), up=(0.0, 1.0, 0.0))
    with_subset = _view(sc)
    _, sub = _mesh(sc, "nerve")
    assert 0 < sub.n_drawn < len(sub.tris)                      # something left out
    # all triangles, no culling: the picture before the subset existed
    sub.sealed[:] = 0
    sub.facing[:] = 1
    sub.n_drawn = len(sub.tris)
    sub.drawn[:] = sub.tris.ravel()
    sc._push_sealed("nerve")
    sc._structures["nerve"].GetProperty().BackfaceCullingOff()
    sc._seal_sig = sc._camera_sig()                             # keep all triangles
    without = _view(sc)
    assert sub.n_drawn == len(sub.tris)
    shown = without[..., 0].astype(int) - without[..., 2] > 80    # yellow nerve
    assert shown.sum() > 20                                     # the nerve is in view
    assert np.array_equal(with_subset, without)


def test_moving_the_bone_unseals_every_structure_triangle(nerve_scene):
    model, state, surf, sc = nerve_scene
    _, sub = _mesh(sc, "nerve")
    assert sub.sealed.any()
    m = np.eye(4)
    m[0, 3] = 2.0                                   # body 0 moved 2 mm along x
    sc._set_main_pose(m)
    assert not sub.sealed.any()
    sc.render()
    assert sub.n_drawn == int(sub.facing.sum())


@pytest.fixture
def coarse_nerve_scene(gl_info):
    """The nerve block with the level of detail forced on (render.toml
    ``[lod]`` for any surface): the nerve meshed on a grid twice as coarse."""
    from types import SimpleNamespace

    from bonesim.render.style import RenderStyle, default_style

    style = RenderStyle(**{**vars(default_style()), "lod": SimpleNamespace(
        **{**vars(default_style().lod), "max_voxel_px": 1000.0, "min_triangles": 0.0,
           "near_mm": 1.0})})
    model, state = nerve_block()
    surf = Surface.build(state.grid, model.colors)
    sc = Scene(size=(240, 180), panel=False, visible_subset=False, style=style)
    sc.update_surface(surf)
    sc.add_structures(model.grid, model.structures)
    yield model, state, surf, sc
    sc.close()


def test_coarse_structure_sealing_matches_the_definition(coarse_nerve_scene, nerve_scene):
    """A mesh made on the coarser grid is sealed with SEAL_RADIUS + 1, and
    unsealed conservatively as the drill opens it."""
    model, state, surf, sc = coarse_nerve_scene
    pts, sub = _mesh(sc, "nerve")
    _, fine = _mesh(nerve_scene[3], "nerve")
    assert sc._coarse_structures and len(sub.tris) < 0.5 * len(fine.tris)
    want = _ref_sealed(model.grid, state.grid, surf, pts, sub.tris, SEAL_RADIUS + 1)
    assert np.array_equal(sub.sealed, want)
    assert 0 < want.sum() < len(want)
    before = sub.sealed.copy()
    removed = _drill(state.grid, (12, 20), (12, 20), 10)
    surf.update(state.grid, removed)
    sc.update_surface(surf, removed)
    fresh = _ref_sealed(model.grid, state.grid, surf, pts, sub.tris, SEAL_RADIUS + 1)
    assert not np.any(sub.sealed.astype(bool) & ~fresh.astype(bool))
    assert np.any(before.astype(bool) & ~sub.sealed.astype(bool))
