"""What the resident sees: dust that the floor shows through (no dark rims,
depth-tested), the hidden burr's silhouette with its depth in the HUD, and
panels beside the field, never over it."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.physics.dust.grid import DustGrid
from bonesim.render.scene import Scene
from bonesim.physics.sightline import depth_below_surface_mm
from bonesim.engine.surface import Surface

SIZE = (400, 300)
TOP_Z = 7.75                   # the nerve block's bone ends at z = 15.5 voxels [mm]
EYE = (8.0, 8.0, 60.0)
FOCAL = (8.0, 8.0, TOP_Z)


@pytest.fixture
def view(gl_info, block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    sc = Scene.from_model(model, surf, size=SIZE, visible_subset=False)
    sc.set_camera(EYE, FOCAL, (0.0, 1.0, 0.0))
    yield sc, model, state
    sc.close()


def _pixels_of(sc, world):
    """Display pixel (column, image row) of a world point."""
    ren = sc.renderer
    ren.SetWorldPoint(*world, 1.0)
    ren.WorldToDisplay()
    x, y, _ = ren.GetDisplayPoint()
    return int(round(x)), SIZE[1] - 1 - int(round(y))


def test_a_layer_of_dust_lets_the_floor_show_and_has_no_dark_rims(view):
    sc, model, state = view
    bare = sc.image().astype(int)
    # a full, fresh layer of dust resting on the bone's top face, as the dust
    # grid hands it over (top layer, jittered)
    dust = DustGrid.for_grid(state.grid, (0.0, 0.0, -1.0))
    ij = np.stack(np.meshgrid(np.arange(8, 24), np.arange(8, 24), indexing="ij"),
                  -1).reshape(-1, 2)
    for k in (16, 17):                            # two cells deep
        dust.add_removed(np.column_stack([ij, np.full(len(ij), k)]), 1.0)
    spr = dust.sprites()
    assert len(spr.positions) == len(ij)          # only the top layer is drawn
    sc.set_dust(*spr)
    dusty = sc.image().astype(int)
    x0, r0 = _pixels_of(sc, (4.5, 4.5, TOP_Z))
    x1, r1 = _pixels_of(sc, (11.0, 11.0, TOP_Z))
    region = np.s_[min(r0, r1) + 3:max(r0, r1) - 3, min(x0, x1) + 3:max(x0, x1) - 3]
    b, d = bare[region], dusty[region]
    dust_rgb = np.rint(np.array(sc.style.dust.dry_rgb) * 255)
    # translucent: the dust moves each pixel less than 60 % of the way from
    # the bone's colour to the dust's
    moved = np.abs(d - b).sum(axis=2)
    full = np.abs(dust_rgb - b).sum(axis=2)
    assert (moved <= 0.6 * full + 6).all()
    assert moved.mean() > 2                       # but it is there
    # no dark rims: nothing darker than both the bone and the dust
    assert (d.sum(axis=2) >= np.minimum(b.sum(axis=2), dust_rgb.sum()) - 6).all()


def test_dust_behind_bone_is_hidden(view):
    sc, model, state = view
    bare = sc.image()
    p = np.array([[8.0, 8.0, TOP_Z - 2.0], [9.0, 8.0, TOP_Z - 3.0]], np.float32)
    sc.set_dust(p, np.ones(2, np.float32), cell_mm=2.0)
    assert sc.dust_actor.GetVisibility()
    assert np.array_equal(sc.image(), bare)       # depth-tested against the bone


def test_hidden_burr_silhouette_and_depth_in_the_hud(view):
    sc, model, state = view
    pos = np.array([8.0, 8.0, 3.0])
    r = 1.5
    depth = depth_below_surface_mm(state.grid, pos, EYE, r)
    assert depth == pytest.approx(TOP_Z - (pos[2] + r), abs=1e-9)
    axis = (1.0, 0.0, -0.3)                      # the shaft leaves toward -x, upward
    sc.set_tool(pos, axis, r, drill_on=True)
    buried = sc.image().astype(int)
    sc.hide_tool()
    bare = sc.image().astype(int)
    x, row = _pixels_of(sc, pos + (0.7 * r, 0.0, 0.0))       # the burr, not its shaft
    spot = np.s_[row - 2:row + 3, x - 2:x + 3]
    assert np.abs(buried[spot] - bare[spot]).max() <= 2      # the bone hides the burr
    sc.set_tool(pos, axis, r, drill_on=True, depth_mm=depth)
    sc.set_hud({"depth_mm": depth})
    assert sc.tool_hidden and f"depth  {depth:.1f} mm under bone" in sc.hud_text
    ghost = sc.image().astype(int)
    hb = np.array(sc.style.hidden_burr.rgb)
    shift = (ghost[spot] - bare[spot]).mean(axis=(0, 1))
    # drawn over the bone, tinted toward the silhouette's colour (cyan: blue
    # and green up against red)
    assert shift[2] - shift[0] > 15 * hb[2] and np.abs(ghost[spot] - bare[spot]).max() > 20
    # only where the burr is: far from it the picture is unchanged
    far = np.s_[5:40, 5:40]
    assert np.array_equal(ghost[far], bare[far])
    # shallow or unknown depth: no silhouette
    for d in (None, 0.0, 0.5 * sc.style.hidden_burr.min_depth_mm):
        sc.set_tool(pos, axis, r, drill_on=True, depth_mm=d)
        assert not sc.tool_hidden
    sc.set_hud({"depth_mm": None})
    assert "depth" not in sc.hud_text
    with pytest.raises(ValueError):
        sc.set_tool(pos, axis, r, depth_mm=float("nan"))


def test_the_hud_and_hint_live_in_the_side_panel(view):
    sc, model, state = view
    sc.set_hud({})
    without = sc.image().astype(int)
    sc.set_hud({"case": "block", "burr": "fake", "drill": True, "force_n": 1.0,
                "depth_mm": 1.2, "elapsed_s": 3.0, "injuries": 0})
    with_hud = sc.image().astype(int)
    px0, py0, px1, py1 = sc.panel_rect()
    vx0, vy0, vx1, vy1 = sc.view_rect()
    assert (vx1, px1) == (px0, SIZE[0]) and px1 - px0 <= 0.4 * SIZE[0]
    changed = np.nonzero(np.abs(with_hud - without).max(axis=2) > 0)[1]
    assert len(changed) > 100 and changed.min() >= px0      # nothing over the field
    # the hint: "h: help", in the panel's bottom rows, in its own colour
    assert sc.hint_text == "h: help"
    hint = with_hud[SIZE[1] - 30:, px0:]
    amber = (hint[..., 0] > 180) & (hint[..., 1] > 140) & (hint[..., 2] < 150)
    assert amber.sum() > 15
    # the HUD's text fits the panel's width
    bb = [0.0] * 4
    sc.hud_actor.GetBoundingBox(sc.panel_renderer, bb)
    assert sc.hud_actor.GetPosition()[0] + bb[1] <= px1 - px0
    sc.set_hint("")
    assert not sc.hint_actor.GetVisibility()


def test_without_a_panel_the_view_fills_the_window(gl_info):
    sc = Scene(size=(200, 100), panel=False, visible_subset=False)
    assert sc.view_rect() == (0, 0, 200, 100) and sc.panel_rect() is None
    assert sc.text_renderer is sc.renderer
    sc.close()


def test_microscope_lights(view):
    sc, model, state = view
    lights = sc.renderer.GetLights()
    assert lights.GetNumberOfItems() == 2 and not sc.renderer.GetAutomaticLightCreation()
    head, fill = sc.lights
    assert head.LightTypeIsHeadlight() and fill.LightTypeIsCameraLight()
    lt = sc.style.lights
    assert head.GetIntensity() == pytest.approx(lt.headlight_intensity)
    # the headlight lights the face toward the eye brightest: the top face
    # seen head-on is brighter than in a view from 60 degrees off the axis
    img = sc.image().astype(int)
    x, row = _pixels_of(sc, (8.0, 8.0, TOP_Z))
    on_axis = img[row - 2:row + 3, x - 2:x + 3].sum(axis=2).mean()
    sc.set_camera((8.0 + 52.0 * np.sin(1.05), 8.0, TOP_Z + 52.0 * np.cos(1.05)), FOCAL,
                  (0.0, 0.0, 1.0))
    img = sc.image().astype(int)
    x, row = _pixels_of(sc, (8.0, 8.0, TOP_Z))
    off_axis = img[row - 2:row + 3, x - 2:x + 3].sum(axis=2).mean()
    assert on_axis > off_axis + 30
