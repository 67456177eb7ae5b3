"""Bodies drawn at their poses: a piece of the phantom split off and moved.

The reference ``images/bodies_moved.png`` is regenerated like the others
(``BONESIM_UPDATE_IMAGES=1``, see ``test_images.py``).
"""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import publish_pose, publish_split_box
from bonesim.engine.model import reset_state
from bonesim.engine.replica import TissueReplica
from tests.bonesim.render import scenes
from tests.bonesim.render.test_images import check


def _matrix(actor):
    m = actor.GetUserMatrix()
    if m is None:
        return np.eye(4)
    return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])


@pytest.fixture(scope="module")
def moved(phantom):
    sc, rep = scenes.bodies_moved(phantom, visible_subset=False)
    yield sc, rep
    sc.close()


def test_moved_piece_matches_reference(moved, tmp_path):
    sc, rep = moved
    img = sc.image()
    assert img.shape == (300, 400, 3)
    check("bodies_moved", img, tmp_path)


def test_piece_is_drawn_at_its_pose_and_leaves_a_hole(moved):
    sc, rep = moved
    assert sorted(rep.body_surfaces) == [0, 1] and list(sc.body_actors) == [1]
    actor = sc.body_actors[1]
    np.testing.assert_allclose(_matrix(actor), rep.body_matrix(1))
    assert sc.surface_actor.GetUserMatrix() is None            # body 0 stays put
    # the piece's bounds in the case frame: its voxels moved by its pose
    g = rep.grid
    lo = g.origin_mm + g.spacing_mm * np.asarray(scenes.PIECE_LO)
    hi = g.origin_mm + g.spacing_mm * np.asarray(scenes.PIECE_HI)
    b = np.array(actor.GetBounds())
    assert b[0] > lo[0] + 0.5 * scenes.PIECE_LIFT_MM[0]         # lifted toward the camera
    assert b[3] - b[2] > 1.1 * (hi[1] - lo[1])                  # turned: wider in y
    with_piece = sc.image()
    actor.SetVisibility(False)
    without = sc.image()
    actor.SetVisibility(True)
    assert (np.abs(with_piece.astype(int) - without).max(axis=2) > 30).mean() > 0.02
    # the hole: the main surface lost the piece's outer face
    s0 = rep.body_surfaces[0]
    i0, j0, k0 = (np.asarray(scenes.PIECE_LO) + scenes.PIECE_HI) // 2
    occupied = [rep.body_grids[0].density_at(i, j0, k0) > 0 for i in range(i0, i0 + 6)]
    assert not any(occupied) and s0.vertex_at(i0, j0, k0) == -1


def test_main_body_pose_moves_the_surface_actor_and_the_visible_subset(phantom):
    from bonesim.engine.model import make_state
    from bonesim.render.scene import Scene

    state = make_state(phantom)
    rep = TissueReplica(phantom, state, surface=True)
    sc = Scene.from_model(phantom, rep.surface, size=scenes.SIZE, structures=False)
    sc.set_hud({})                     # no measured frame rate: the same text every frame
    try:
        sc.set_camera(scenes.CLOSE_EYE, scenes.CLOSE_FOCAL, scenes.UP)
        out = sc.update_bodies(rep)
        assert out["bodies"] == 1 and sc.body_actors == {}
        ref = sc.image()
        pose = (0.0, 0.0, 3.0, 1.0, 0.0, 0.0, 0.0)
        publish_pose(state, 0, pose, 0.0)
        ch = rep.drain()
        sc.update_bodies(rep, ch.changed, ch.touched)
        np.testing.assert_allclose(_matrix(sc.surface_actor), rep.body_matrix(0))
        full = sc.image()
        assert (np.abs(full.astype(int) - ref).max(axis=2) > 30).mean() > 0.01
        # the subset is computed in body 0's frame: the same picture
        assert sc.refresh_visible()
        vis = sc.image()
        assert (np.abs(vis.astype(int) - full).max(axis=2) > 30).mean() < 0.002
    finally:
        sc.close()


def test_split_then_reset_adds_and_drops_actors(phantom):
    from bonesim.engine.model import make_state
    from bonesim.render.scene import Scene

    state = make_state(phantom)
    rep = TissueReplica(phantom, state, surface=True)
    sc = Scene.from_model(phantom, rep.surface, size=scenes.SIZE, structures=False)
    try:
        b, _ = publish_split_box(state, 0, scenes.PIECE_LO, scenes.PIECE_HI, 0.0)
        ch = rep.drain()
        out = sc.update_bodies(rep, ch.changed, ch.touched)
        assert out["rebuilt"] == 1 and list(sc.body_actors) == [b]
        assert sc.surface is rep.surface
        out = sc.update_bodies(rep, ch.changed[:0], ch.touched)   # nothing new: no copy
        assert out["rebuilt"] == 0
        reset_state(phantom, state, rings=False)
        events.push_event(state.tissue, events.RESET, 0.0, n=1)
        ch = rep.drain()
        assert ch.reset
        sc.update_bodies(rep)
        assert sc.body_actors == {} and sc.surface is rep.surface
    finally:
        sc.close()
