"""Offscreen pictures of a cut-plane box cut and of an irrigated basin with
pooled water and wet dust, against stored references (``images/``).

Regenerate after an intended change of the picture with::

    BONESIM_UPDATE_IMAGES=1 python -m pytest tests/bonesim/render/test_cut_water_images.py
"""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.render.imagecmp import compare_images
from tests.bonesim.render import cut_water_scenes as cws
from tests.bonesim.render.test_images import check


@pytest.fixture(scope="module")
def rendered(phantom):
    from bonesim.engine.model import make_state
    from bonesim.engine.surface import Surface
    from bonesim.render.scene import Scene

    out = {}
    sc, _, removed = cws.cut_scene(phantom)
    out["cut_plane"] = sc.image()
    out["cut_removed"] = len(removed)
    sc.close()
    # the same view of the intact bone
    state = make_state(phantom)
    sc = Scene.from_model(phantom, Surface.of_model(phantom, state.grid), size=cws.SIZE)
    sc.set_hud({})
    sc.set_camera(cws.CUT_EYE, cws.CUT_FOCAL, cws.UP)
    out["cut_intact"] = sc.image()
    sc.close()
    sc, dust = cws.water_scene(phantom)
    out["irrigated"] = sc.image()
    sc.set_water(np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    out["irrigated_nowater"] = sc.image()
    out["dust"] = dust
    sc.close()
    return out


@pytest.mark.parametrize("name", ("cut_plane", "irrigated"))
def test_matches_reference(rendered, name, tmp_path):
    assert rendered[name].shape == (300, 400, 3)
    check(name, rendered[name], tmp_path)


def bluish(img):
    """Fraction of pixels clearly bluer than bone (blue above red by 50)."""
    i = img.astype(int)
    return float(((i[..., 2] - i[..., 0] > 50) & (i[..., 2] > 150)).mean())


def test_pictures_show_what_they_claim(rendered):
    from bonesim.physics.dust.water import water_cells

    # the cuts change the picture of the intact cortex: dark grooves and a recess
    res = compare_images(rendered["cut_plane"], rendered["cut_intact"])
    assert not res and res.frac > 0.01, res
    assert rendered["cut_removed"] > 1000
    # the basin holds water (blue sheet) over wet dust; without the water
    # sprites the blue is gone
    assert water_cells(rendered["dust"]) > 100 and rendered["dust"].wet_cells > 100
    assert bluish(rendered["irrigated"]) > 0.04              # the basin's sheet
    assert bluish(rendered["irrigated_nowater"]) < 0.002
