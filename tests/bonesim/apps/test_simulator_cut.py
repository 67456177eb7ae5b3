"""The window's cut plane: ``k`` makes it the tool, the mouse poses it,
Return cuts a stroke through the loop's command ring."""
from __future__ import annotations

import time

import numpy as np
import pytest

from bonesim.engine import events

pytestmark = pytest.mark.slow


def test_the_cut_plane_from_the_window(tmp_path):
    from bonesim.apps.simulator import CUT_STANDOFF_MM, App
    from bonesim.io.case import load_case

    cam = load_case("phantom").camera
    app = App("phantom", "cutting-5mm", offscreen=True, size=(320, 240), sound=False)
    try:
        app.start()
        app.window.run_offscreen(3, realtime=True)
        app.window.press("cut_plane")
        assert app.cut_pose is not None and not bool(app.loop.control["drill"])
        # the mouse on the bone's surface point under the case's focus
        at = np.asarray(cam.focal_mm, float) + 1.5 * app.view
        app.on_mouse(at, 0)
        np.testing.assert_allclose(app.cut_pose[:3], at - CUT_STANDOFF_MM * app.view)
        n0 = app.loop.state.n_removed
        start = app.loop.state.tissue.count
        app.window.press("cut_stroke")
        end = time.monotonic() + 30.0          # a loaded machine: the loop takes it late
        while True:
            app.window.run_offscreen(2, realtime=True)
            ev = app.loop.state.tissue.read(start)
            if (ev["kind"] == events.CUT).any() or time.monotonic() > end:
                break
        assert (ev["kind"] == events.CUT).sum() == 1
        assert app.loop.state.n_removed - n0 == int(ev["n"][ev["kind"] == events.CUT][0]) > 50
        assert "cut plane" in app.scene.hud_text
        assert app.scene.cut_plane.actor.GetVisibility()
        app.window.press("cut_plane")                 # the burr back
        app.window.run_offscreen(2, realtime=True)
        assert app.cut_pose is None and not app.scene.cut_plane.actor.GetVisibility()
    finally:
        app.close()
