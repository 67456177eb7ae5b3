"""The scene's structures (bonesim.render.structures_view): meshed from the
labels in their colours, listed, shown and hidden, replaced by name."""
from __future__ import annotations

import pytest

from bonesim.engine.surface import Surface
from bonesim.render.scene import Scene


@pytest.fixture
def scene(gl_info):
    sc = Scene(size=(160, 120))
    yield sc
    sc.close()


def test_structures_are_meshed_from_labels(scene, block):
    model, state = block
    counts = scene.add_structures(model.grid, model.structures)
    assert list(counts) == ["nerve"] and counts["nerve"] > 50
    actor = scene._structures["nerve"]
    b = actor.GetMapper().GetInput().GetBounds()
    # rod: x all along, y 14..17, z 8..9 voxels of 0.5 mm
    assert b[2] > 6.5 and b[3] < 9.0 and b[4] > 3.5 and b[5] < 5.0
    assert actor.GetProperty().GetColor() == pytest.approx((240 / 255, 220 / 255, 40 / 255))


def test_structures_listed_hidden_and_replaced_by_name(scene, block):
    model, state = block
    scene.update_surface(Surface.build(state.grid, model.colors))
    scene.add_structures(model.grid, model.structures)
    assert scene.structure_names == ["nerve"] and "nerve" in scene._sealed
    first = scene._structures["nerve"]
    assert first.GetVisibility() and first.GetProperty().GetBackfaceCulling()
    scene.set_structure_visible("nerve", False)
    assert not first.GetVisibility()
    # the same name again: the new mesh replaces the old actor and its subset
    second = scene.add_mesh("nerve", ([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                                      [[0, 1, 2]]), (10, 20, 30))
    actors = scene.renderer.GetActors()
    actors.InitTraversal()
    drawn = [actors.GetNextActor() for _ in range(actors.GetNumberOfItems())]
    assert second in drawn and first not in drawn
    assert scene.structure_names == ["nerve"] and "nerve" not in scene._sealed
    assert second.GetProperty().GetColor() == pytest.approx((10 / 255, 20 / 255, 30 / 255))
