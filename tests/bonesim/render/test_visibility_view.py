"""The visibility view: built from arrays, turned about with the mouse in its window."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.render.imagecmp import read_png
from bonesim.render.visibility_view import (HIDDEN_RGB, VISIBLE_RGB, show_visibility,
                                            viewer_window, visibility_scene)
from tests.bonesim.fakes import BONE, NERVE, block_model
from tests.bonesim.render.test_window import mouse


@pytest.fixture
def view(gl_info):
    labels = np.zeros((24, 24, 24), np.uint8)
    labels[4:20, 4:20, 4:20] = 1
    labels[10:14, 10:14, 6:9] = 2                       # a nerve inside the block
    model, _ = block_model(labels=labels, structures=[BONE, NERVE], spacing=0.5)
    ijk = np.argwhere(labels[:, :, 14:20] == 1) + (0, 0, 14)
    centre = ijk * 0.5
    visible = (ijk[:, 0] < 12).astype(np.int8)          # half seen, half hidden
    scene = visibility_scene(model, centre, visible, ["nerve"], "Voxel visibility",
                             ["50.0 % visible"], size=(320, 240), offscreen=True)
    yield scene
    scene.close()


def test_view_shows_seen_and_hidden_removals_in_their_colours(view, tmp_path):
    out = show_visibility(view, frames=2, screenshot=tmp_path / "v.png")
    img = read_png(out["screenshot"])[..., :3].astype(int)
    for rgb in (VISIBLE_RGB, HIDDEN_RGB):
        near = np.all(np.abs(img - rgb) < 60, axis=-1)
        assert near.sum() > 200, rgb


def test_the_mouse_turns_and_zooms_the_view(view):
    win = viewer_window(view)
    view.render()
    cam = view.camera
    start = np.array(cam.GetPosition())
    focal = np.array(cam.GetFocalPoint())
    r0 = np.linalg.norm(start - focal)
    mouse(win, "LeftButtonPressEvent", 160, 120)        # a plain left drag orbits
    mouse(win, "MouseMoveEvent", 220, 120)
    mouse(win, "LeftButtonReleaseEvent", 220, 120)
    turned = np.array(cam.GetPosition())
    assert np.linalg.norm(turned - start) > 0.1 * r0
    assert np.linalg.norm(turned - focal) == pytest.approx(r0, rel=1e-3)
    mouse(win, "MouseWheelForwardEvent", 160, 120)      # the wheel zooms
    assert np.linalg.norm(np.array(cam.GetPosition()) - focal) < 0.99 * r0
    win.press("reset_view")                             # v: back where it started
    view.render()
    np.testing.assert_allclose(cam.GetPosition(), start, atol=1e-6 * r0)


def test_mismatched_arrays_are_refused(gl_info):
    model, _ = block_model()
    with pytest.raises(ValueError, match="visible has 1 entries, centre_mm 2"):
        visibility_scene(model, np.zeros((2, 3)), [1], [], "t", [])
