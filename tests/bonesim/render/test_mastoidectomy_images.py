"""The whole demo mastoidectomy from the surgeon's view, before and after,
against stored references (``images/mastoidectomy_*.png``, 800 x 300):

* the phantom's main job (:class:`bonesim.apps.showcase.Showcase` through the
  whole plan, both burrs, in the engine): the cavity the engine drilled, which
  must be the bone the plan sweeps;
* a peer export with one merged sinus-and-dura label: the cavity the plan
  sweeps (every bone voxel a drilling burr's sphere reaches), drawn on the
  same surface.

Regenerate with ``BONESIM_UPDATE_IMAGES=1`` (see ``test_images.py``) and look
at them: the cavity in Macewen's triangle and back over the sinus, saucerized,
the blue line over the sinus, the tegmen's pink-grey, the facial nerve and
chorda showing through their bone, the antrum opened.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from bonesim.apps.showcase import ZOOM, Showcase
from bonesim.engine import events
from bonesim.engine.model import make_state
from bonesim.engine.replica import TissueReplica
from bonesim.io.case import load_case
from bonesim.io.loading import load_model
from tests.bonesim.io.test_mastoid_plan import cavity_report, planned
from tests.bonesim.real_like import write_real_like
from tests.bonesim.render.test_images import check

SIZE = (400, 300)


def _view(model, surface):
    from bonesim.render.scene import Scene

    scene = Scene.from_model(model, surface, offscreen=True, size=SIZE)
    cam = model.case.camera
    focal = np.asarray(cam.focal_mm, float)
    scene.set_case_camera(focal + (np.asarray(cam.eye_mm, float) - focal) / ZOOM, focal,
                          cam.up)
    scene.set_hud({"case": model.name, "burr": model.burr.name, "message": ""})
    return scene


def picture(model, state) -> np.ndarray:
    """The bone of ``state`` (a fresh replica's surface) from the case camera."""
    replica = TissueReplica(model, state, surface=True)
    scene = _view(model, replica.surface)
    try:
        return scene.image()
    finally:
        scene.close()


@pytest.mark.slow
def test_the_phantoms_main_job(gl_info, tmp_path):
    """Through the whole plan in the engine: it removes the bone the plan
    sweeps, only bone, injures nothing; before and after stored."""
    case = load_case("phantom")
    pr, radii = planned(case)
    with Showcase("phantom", "cutting-5mm", size=(160, 120), monitor=False) as sh:
        before = picture(sh.model, make_state(sh.model))
        sh.simulate(sh.end_s)             # the engine alone: the dust is not pictured
        density = sh.state.grid.to_dense()[0]
        assert sh.state.removed_by_label[2:].sum() == 0
        assert len(events.injuries(sh.state.tissue.read(0))["t_s"]) == 0
        after = picture(sh.model, sh.state)
    rep = cavity_report(case, pr, radii)
    removed = (case.load_volume().labels == 1) & (density <= 0)
    assert removed[rep["cut"]].mean() > 0.9                # the plan's cavity ...
    grown = ndimage.binary_dilation(rep["cut"], iterations=2)
    assert (removed & ~grown).sum() < 0.01 * removed.sum()  # ... and nothing beyond
    check("mastoidectomy_phantom", np.concatenate([before, after], axis=1), tmp_path)


def test_a_merged_label_exports_planned_cavity(gl_info, tmp_path):
    case = load_case(write_real_like(tmp_path / "case"))
    pr, radii = planned(case)
    rep = cavity_report(case, pr, radii)
    model = load_model(case, "cutting-5mm")
    state = make_state(model)
    before = picture(model, state)
    from bonesim.bench.tools import remove_voxels

    remove_voxels(state.grid, np.argwhere(rep["cut"]))
    after = picture(model, state)
    assert np.abs(before.astype(int) - after.astype(int)).mean() > 3.0
    check("mastoidectomy_merged_label", np.concatenate([before, after], axis=1), tmp_path)
