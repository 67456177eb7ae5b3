"""Scene: zero-copy surface buffers, visible subset, tool, dust, camera, text."""
from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util import numpy_support

from bonesim.render.scene import Scene, tool_matrix
from bonesim.engine.surface import Surface
from tests.bonesim.render.test_meshbuf import live, pit, remove, triples


@pytest.fixture
def scene(gl_info):
    sc = Scene(size=(160, 120))
    yield sc
    sc.close()


def drawn_triangles(sc):
    cells = sc._pd.GetPolys()
    conn = numpy_support.vtk_to_numpy(cells.GetConnectivityArray())
    return conn.reshape(-1, 3)


def test_surface_is_shared_not_copied(scene, block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    info = scene.update_surface(surf)
    assert info == {"triangles": surf.n_triangles, "drawn": surf.n_triangles, "mode": "full"}
    pts = scene._pd.GetPoints()
    assert pts.GetNumberOfPoints() == surf.pos.shape[0]
    v = int(surf.vertex_slots[0])
    surf.pos[v] = (1.5, 2.5, 3.5)               # VTK sees the surface's own memory
    assert pts.GetPoint(v) == (1.5, 2.5, 3.5)
    col = numpy_support.vtk_to_numpy(scene._pd.GetPointData().GetScalars())
    assert np.shares_memory(col, surf.col)
    assert triples(drawn_triangles(scene)) == triples(live(surf))


def test_incremental_update_and_growth_rebind(scene, block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    scene.update_surface(surf)
    scene.render()
    pos0 = surf.pos
    for i in range(1, 31, 2):
        surf.update(grid, remove(grid, pit(i, i + 1, 1, 31, 2, 16)))
    assert surf.pos is not pos0                  # the surface grew its arrays
    scene.update_surface(surf)
    scene.render()
    pts = scene._pd.GetPoints()
    assert pts.GetNumberOfPoints() == surf.pos.shape[0]
    assert np.shares_memory(numpy_support.vtk_to_numpy(pts.GetData()), surf.pos)
    assert triples(drawn_triangles(scene)) == triples(live(surf))
    # the bounds hold every drawn point (VTK counts every point of the
    # array: free slots hold zeros, which here lie at the block's corner)
    b = np.array(scene._pd.GetBounds())
    p = surf.pos[np.unique(live(surf))]
    assert (b[0::2] <= p.min(0) + 1e-6).all() and (b[1::2] >= p.max(0) - 1e-6).all()
    assert np.allclose(b[1::2], p.max(0))


def test_visible_subset_while_resting_full_while_moving(scene, block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    scene.update_surface(surf)
    scene.set_camera((8.0, 8.0, 60.0), (8.0, 8.0, 4.0), (0.0, 1.0, 0.0))
    scene.render()
    assert scene.drawing == "full"
    assert scene.refresh_visible()
    assert scene.drawing == "visible" and scene.stats["n_vis"] < scene.stats["n_full"]
    n_vis = len(drawn_triangles(scene))
    assert n_vis == scene.stats["n_vis"]
    scene.camera.Azimuth(20.0)                  # the camera moves: full list again
    scene.render()
    assert scene.drawing == "full" and len(drawn_triangles(scene)) == surf.n_triangles


def test_visible_subset_is_built_by_itself_when_the_camera_rests(gl_info, block):
    import time

    model, state = block
    sc = Scene(size=(160, 120), rest_s=0.05)
    try:
        sc.update_surface(Surface.build(state.grid, model.colors))
        sc.fit_camera()
        t_end = time.perf_counter() + 20.0
        while sc.drawing != "visible" and time.perf_counter() < t_end:
            sc.render()
            time.sleep(0.02)
        assert sc.drawing == "visible" and sc.stats["visible_jobs"] == 1
    finally:
        sc.close()


def test_tool_pose(scene):
    scene.set_tool((1.0, 2.0, 3.0), (0.0, 0.0, -2.0), 1.5, drill_on=True)
    burr = scene._burr
    b = np.array(burr.GetBounds())
    assert np.allclose(0.5 * (b[0::2] + b[1::2]), (1, 2, 3), atol=1e-6)
    assert np.allclose(b[1::2] - b[0::2], 3.0, atol=0.05)
    s = np.array(scene._shaft.GetBounds())       # the shaft rises along -axis (+z)
    assert s[4] == pytest.approx(3.0, abs=1e-6) and s[5] > 30.0
    m = tool_matrix((0, 0, 0), (1.0, 1.0, 0.0))
    assert np.allclose(m[:3, 1], -np.array([1, 1, 0]) / np.sqrt(2))
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
    scene.set_tool((0, 0, 0), (1, 0, 0), 2.0, kind="suction")
    assert not burr.GetVisibility() and scene._shaft.GetVisibility()
    with pytest.raises(ValueError):
        scene.set_tool((0, 0, 0), (1, 0, 0), 0.0)
    with pytest.raises(ValueError):
        scene.set_tool((0, 0, 0), (1, 0, 0), 1.0, kind="laser")


def test_dust_sprites(scene):
    from bonesim.render.dustview import sprite_look

    st = scene.style.dust
    p = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], np.float32)
    d = np.array([1.0, 0.0, 0.5, 2.0], np.float32)
    age = np.array([0.0, 1.0, 2.0 * st.fade_s, 1e4], np.float32)
    wet = np.array([0, 0, 1, 0], np.uint8)
    scene.set_dust(p, d, cell_mm=1.0, age_s=age, wet=wet)
    pd = scene.dust.polydata
    assert pd.GetNumberOfPoints() == 3 == scene.dust.count      # empty cells are not drawn
    r = numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("radius"))
    rgba = numpy_support.vtk_to_numpy(pd.GetPointData().GetScalars())
    # radius: radius_cells * cell * cbrt(min(d, 1))
    np.testing.assert_allclose(r, st.radius_cells * np.array([1.0, 0.5 ** (1 / 3), 1.0]),
                               rtol=1e-6)
    # opacity: fresh full dry cell = opacity; old dust fades to `aged`; wet paste
    # darker and fainter
    want = [st.opacity,
            st.opacity * 0.5 ** 0.5 * (st.aged + (1 - st.aged) * np.exp(-2.0))
            * st.wet_opacity,
            st.opacity * st.aged]
    np.testing.assert_allclose(rgba[:, 3] / 255.0, want, atol=1 / 255)
    assert tuple(rgba[0, :3]) == tuple(np.rint(np.array(st.dry_rgb) * 255))
    assert tuple(rgba[1, :3]) == tuple(np.rint(np.array(st.wet_rgb) * 255))
    assert rgba[1, :3].sum() < rgba[0, :3].sum()
    rr, cc = sprite_look(d[[0, 2, 3]], age[[0, 2, 3]], wet[[0, 2, 3]], 1.0, st)
    np.testing.assert_array_equal(cc, rgba)
    # the default (DustGrid.sprites without ages): fresh, dry, cell = voxel
    scene.set_dust(p[:1], d[:1])
    assert numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("radius"))[0] == \
        pytest.approx(st.radius_cells * scene.voxel_mm)
    scene.set_dust(np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    assert not scene.dust_actor.GetVisibility()
    with pytest.raises(ValueError):
        scene.set_dust(p, np.ones(2, np.float32))
    with pytest.raises(ValueError):
        scene.set_dust(p, d, age_s=np.ones(2))


def test_dust_looks_as_with_vtk_defaults(gl_info, block):
    """Draw-order blending (the scene's with the level of detail on) and
    sprite squares just around their disks give about the picture VTK's
    defaults give (order-independent blending,
    squares of three radii): a heap of overlapping wet and dry sprites on a
    block."""
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    sc = Scene(size=(240, 180), panel=False)
    try:
        sc.update_surface(surf)
        sc.set_camera((8.0, 4.0, 40.0), (8.0, 7.9, 4.0), up=(0.0, 1.0, 0.0))
        rng = np.random.default_rng(3)
        p = (np.array([8.0, 8.0, 8.2]) + rng.normal(0.0, 1.5, (3000, 3))).astype(np.float32)
        sc.set_dust(p, rng.uniform(0.2, 1.0, 3000).astype(np.float32), cell_mm=0.5,
                    wet=rng.random(3000) < 0.3)
        # full detail here, so order-independent blending (VTK's default)
        assert sc.renderer.GetUseOIT() and sc.dust.mapper.GetBoundScale() == 1.0
        sc.renderer.SetUseOIT(False)             # as with the level of detail on
        ours = sc.image().astype(int)
        sc.renderer.SetUseOIT(True)
        sc.dust.mapper.SetBoundScale(3.0)
        vtk_default = sc.image().astype(int)
        sc.dust_actor.SetVisibility(False)
        no_dust = sc.image().astype(int)
    finally:
        sc.close()
    dusty = np.abs(vtk_default - no_dust).max(axis=2) > 4
    assert dusty.sum() > 500                                  # the dust shows
    diff = np.abs(ours - vtk_default).max(axis=2)
    # a thick heap of mixed wet and dry sprites is where blending order shows
    # most (about 3/255 on average, 19/255 at the 99th percentile here; the
    # drilled phantom's settled dust differs by at most 3/255)
    assert diff[dusty].mean() < 4.0 and np.percentile(diff[dusty], 99) < 25
    assert diff.max() < 40


def test_mouse_plane_through_the_tool(scene):
    scene.set_camera((0.0, 0.0, 100.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    scene.set_tool((3.0, -2.0, 10.0), (0, 0, -1), 1.0)
    scene.render()
    x0, y0, x1, y1 = scene.view_rect()              # the 3D view, left of the panel
    centre = scene.display_to_plane((x0 + x1) / 2, (y0 + y1) / 2)
    assert centre == pytest.approx((0.0, 0.0, 10.0), abs=0.4)
    p = scene.display_to_plane(x1 - 5, 20)
    assert p[2] == pytest.approx(10.0, abs=1e-6)
    assert p[0] > 5.0 and p[1] < -5.0             # right and down in the view
    q = scene.display_to_plane(x1 - 5, 20, through_mm=(0, 0, -20.0))
    assert q[2] == pytest.approx(-20.0, abs=1e-6) and abs(q[0]) > abs(p[0])


def test_hud_help_and_frame_rate(scene):
    scene.set_hud({"case": "x", "haptic_hz": 1000})
    for _ in range(3):
        scene.render()
    assert scene.frame_hz is not None and scene.frame_hz > 0
    scene.set_hud({"case": "x", "haptic_hz": 1000})
    assert "haptic 1000 Hz" in scene.hud_text and "frame" in scene.hud_text
    scene.set_help("keys\n  h  help")
    assert scene.show_help() is True and scene.help_actor.GetVisibility()
    assert scene.toggle_help() is False


def test_camera_reset_and_screenshot(scene, tmp_path):
    scene.set_case_camera((50, 0, 0), (0, 0, 0), (0, 0, 1))
    scene.camera.Azimuth(30)
    scene.reset_camera()
    assert scene.camera.GetPosition() == pytest.approx((50, 0, 0))
    assert scene.view_direction() == pytest.approx((-1, 0, 0))
    img = scene.image()
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    path = scene.screenshot(tmp_path / "s" / "shot.png")
    from bonesim.render.imagecmp import read_png

    assert read_png(path).shape == (120, 160, 3)


def test_a_new_surface_replaces_the_old_one(scene, block):
    model, state = block
    grid = state.grid
    a = Surface.build(grid, model.colors)
    scene.update_surface(a)
    scene.render()
    assert scene.refresh_visible()
    lower = grid.copy()
    remove(lower, pit(0, 32, 0, 32, 10, 16))                # a lower block
    b = Surface.build(lower, model.colors)
    info = scene.update_surface(b)
    assert info["mode"] == "full" and scene.surface is b
    assert triples(drawn_triangles(scene)) == triples(live(b))
    assert np.shares_memory(numpy_support.vtk_to_numpy(scene._pd.GetPoints().GetData()),
                            b.pos)
    scene.render()


def test_subset_adopted_after_an_unpushed_update_shows_current_vertices(scene, block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    scene.update_surface(surf)
    scene.render()
    for i in range(1, 31, 2):                 # grow the surface without update_surface
        surf.update(grid, remove(grid, pit(i, i + 1, 1, 31, 2, 16)))
    assert scene.refresh_visible()
    assert np.shares_memory(numpy_support.vtk_to_numpy(scene._pd.GetPoints().GetData()),
                            surf.pos)
    assert int(drawn_triangles(scene).max()) < surf.pos.shape[0]
    scene.render()
