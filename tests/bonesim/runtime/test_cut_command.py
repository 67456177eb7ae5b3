"""Cut-plane strokes through the haptic loop's command ring: recorded,
replayed bit for bit, followed by a replica."""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.cut_plane import plane_pose, rays_per_step
from bonesim.engine.replica import TissueReplica
from bonesim.io.case import load_case
from bonesim.io.loading import load_model
from bonesim.engine.world_commands import TOOLS
from bonesim.runtime.commands import CutPlane, SetTool
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify
from tests.bonesim.waiting import wait_drill_off, wait_until


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def cut_run(model, tmp_path_factory):
    """Mouse drilling, then a box cut of three strokes through the ring
    (one of them across the drilled spot), then more drilling; recorded."""
    path = tmp_path_factory.mktemp("cut") / "cut.h5"
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    target = np.array([23.0, 3.0, -2.0]) + 3.0 * view
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    try:
        rec.start()
        loop.start()
        live = TissueReplica(model, loop.state, snapshot=False)
        loop.set_target(target, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 20)
        loop.set_tool("cutplane")
        assert wait_until(lambda: int(loop.status["tool"]) == TOOLS.index("cutplane"))
        at = np.asarray(loop.status["pos_mm"], float)
        n0 = loop.state.n_removed
        for k, normal in enumerate((view, view + (0.5, 0, 0), view + (0, 0.5, 0))):
            loop.send(CutPlane, pose=plane_pose(at - 2.0 * view + (k, 0, 0), normal),
                      width_mm=6.0, height_mm=5.0, depth_mm=4.0)
        assert wait_until(lambda: int(loop.status["commands_applied"]) == 4)
        n1 = loop.state.n_removed
        loop.set_tool("drill")
        loop.set_target(target + 6.0 * view, view)      # on to the bone under the cut
        assert wait_until(lambda: loop.state.n_removed > n1 + 50)
        loop.set_drill(False)
        assert wait_drill_off(loop)

        def caught_up():
            live.drain()
            return np.array_equal(live.grid.density == 0, loop.state.grid.density == 0)

        # a stroke's last slices, or a loose piece the fragment finder sheds,
        # may still be applying after the drill is off (a loaded machine):
        # the replica must reach the loop's tissue
        if not wait_until(caught_up):
            np.testing.assert_array_equal(live.grid.density == 0,
                                          loop.state.grid.density == 0)
        rec.close()
        applied = int(loop.status["commands_applied"])
        rejected = int(loop.status["commands_rejected"])
    finally:
        loop.close()
    return read_session(path), n0, n1, applied, rejected


def test_strokes_through_the_ring_are_recorded(cut_run):
    s, n0, n1, applied, rejected = cut_run
    assert rejected == 0 and applied == 5           # two tool changes, three strokes
    k = s.tissue["kind"]
    cuts = np.flatnonzero(k == events.CUT)
    assert len(cuts) == 3
    np.testing.assert_array_equal(s.tissue["ijk"][cuts], [[6000, 5000, 4000]] * 3)
    # each stroke (24 x 20 rays of 4 mm) is more than a world step walks: done
    # in slices (bonesim.engine.cut_plane), its record first with n = -(rays
    # per step), its removals over the next steps (the later strokes wait)
    per = rays_per_step(4.0, 0.5)
    assert 24 * 20 > per
    assert (s.tissue["n"][cuts] == -per).all()
    t_cut = s.tissue["t_s"][cuts]
    rem = (k == events.REMOVED) & (s.tissue["t_s"] >= t_cut[0])
    steps = np.unique(s.tissue["t_s"][rem])
    assert rem.sum() > 200 and len(steps) >= 3 * -(-24 * 20 // per)
    assert n1 - n0 > 0


def test_a_run_with_strokes_replays_bit_for_bit(cut_run):
    s = cut_run[0]
    report = verify(s)
    assert report["ok"], report
    out = replay(s)
    assert (out["tissue"]["kind"] == events.CUT).sum() == 3


def test_bad_strokes_are_refused_where_sent():
    with pytest.raises(ValueError, match="width_mm"):
        CutPlane.encode(pose=plane_pose((0, 0, 0), (0, 0, 1)), width_mm=-1.0, height_mm=1.0,
                        depth_mm=1.0)
    with pytest.raises(ValueError, match="unknown tool"):
        SetTool.encode(tool="laser")


def test_a_run_with_strokes_plays_back(cut_run, model):
    from bonesim.session.playback import Player

    s = cut_run[0]
    p = Player(s, model, [model.burr])
    p.seek(p.timeline.duration)
    out = replay(s)["state"]
    np.testing.assert_array_equal(p.replica.grid.density == 0, out.grid.density == 0)
