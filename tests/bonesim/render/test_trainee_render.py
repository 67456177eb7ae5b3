"""The trainee's window offscreen: the replica follows the servo's changes
ring (tissue events: removals, resets, splits, poses), the instructor's tool
and the trainee's hand are
placed from its status, the HUD says when the link is lost; and the
``tutor playback`` command's window on a recorded run."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.net.tutor_protocol import GLOSSARY
from bonesim.tutoring import trainee as T
from bonesim.runtime.child import BASE_STATUS, record_dtype
from bonesim.render.scene import Scene
from bonesim.render.trainee import TraineeView
from bonesim.engine.surface import Surface
from tests.bonesim.render.scenes import nerve_block
from tests.bonesim.session.test_playback import demo_file  # noqa: F401 (fixture)

SIZE = (320, 240)


def last_message(hud: str) -> str:
    """The HUD's last message line, with its wrapped continuations joined."""
    lines = hud.splitlines()
    start = max(i for i, ln in enumerate(lines) if not ln.startswith("  "))
    return " ".join(ln.strip() for ln in lines[start:])


def _fake_proc(model):
    """What TraineeView reads of a TraineeProcess, with no process."""
    status = np.zeros((), record_dtype(BASE_STATUS, T.STATUS))
    changes = events.tissue_ring(1 << 12)
    return SimpleNamespace(model=model, status=status, changes=changes, burrs=["fake"],
                           radii=[1.5], radius_mm=lambda b: 1.5, what="instructor at test",
                           lost_text="LINK LOST", source=("network",),
                           duration_of_source_s=math.nan)


def _bone_voxels(model, k, n):
    """The first ``n`` bone voxels of layer ``k`` (occupied in the model)."""
    ii, jj = np.meshgrid(np.arange(4, 28), np.arange(2, 12), indexing="ij")
    ijk = np.stack([ii.ravel(), jj.ravel(), np.full(ii.size, k)], 1).astype(np.int32)
    return ijk[:n]


def _removed(ijk, t_s=0.0):
    """REMOVED events of voxels ``ijk``."""
    ev = events.empty_events(len(ijk))
    ev["kind"][:] = events.REMOVED
    ev["ijk"][:] = ijk
    ev["t_s"][:] = t_s
    return ev


def _one(kind, body=0, n=0, value=()):
    ev = events.empty_events(1)
    ev["kind"][0], ev["body"][0], ev["n"][0] = kind, body, n
    ev["value"][0, :len(value)] = value
    return ev


def _occupied(grid, ijk):
    return np.array([grid.density[grid.brick_index(*v), (v[0] & 7) << 6 | (v[1] & 7) << 3
                                  | (v[2] & 7)] > 0 for v in ijk])


@pytest.fixture
def view(gl_info):
    model, _ = nerve_block()
    proc = _fake_proc(model)
    scene = Scene.from_model(model, size=SIZE, visible_subset=False)
    v = TraineeView(scene, proc)
    yield v, proc
    scene.close()


def test_replica_follows_removals_and_resets(view):
    v, proc = view
    model = proc.model
    top = _bone_voxels(model, 15, 120)
    proc.changes.append(**_removed(top[:70]))
    assert v.drain() == 70
    proc.changes.append(**_removed(top[70:]))
    v.show()
    assert v.applied == 120 and not _occupied(v.grid, top).any()
    # the drawn surface is the replica's, and equals one built from scratch
    assert v.scene.surface is v.surface
    fresh = Surface.of_model(model, v.grid)            # as the replica: with the tint
    assert not fresh.canonical().differences(v.surface.canonical())
    assert v.scene._buffers.n_full == v.surface.n_triangles
    # a reset in the middle of a batch: what came before it is moot
    below = _bone_voxels(model, 14, 30)
    proc.changes.append(**_removed(top[:10]))
    proc.changes.append(**_one(events.RESET, n=1))
    proc.changes.append(**_removed(below))
    assert v.drain() == 30 and v.resets == 1 and v.applied == 30
    assert v.replica.epoch == 1 and v.scene.surface is v.surface
    assert _occupied(v.grid, top).all() and not _occupied(v.grid, below).any()
    fresh = Surface.of_model(model, v.grid)            # as the replica: with the tint
    assert not fresh.canonical().differences(v.surface.canonical())
    # the model itself is untouched
    assert _occupied(model.grid, below).all()
    # a split and a pose reach the window's replica like the removals
    split = _removed(top[:5])
    split["kind"][:] = events.SPLIT
    split["body"][:] = 1
    split["n"][:] = 5
    proc.changes.append(**split)
    proc.changes.append(**_one(events.POSE, body=1, value=(1.0, 0, 0, 1, 0, 0, 0)))
    assert v.drain() == 0 and v.applied == 30
    assert v.replica.state.alive[1] and v.replica.state.pose[1, 0] == 1.0
    assert (v.replica.state.body[v.grid.density > 0] == 1).sum() == 5


def test_tool_hand_and_hud_come_from_the_status(view):
    v, proc = view
    s = proc.status
    sc = v.scene
    info = v.show()                          # nothing received yet: no tool drawn
    assert sc.tool_pos_mm is None and sc.marker_pos_mm is None
    s["valid"] = 1
    s["instr_pos_mm"] = (8.0, 6.0, 9.0)
    s["instr_axis"] = (0.0, 0.0, -1.0)
    s["hand_mm"] = (9.0, 6.5, 10.0)
    s["force_n"] = (0.3, 0.0, 0.4)
    s["drill"] = 1
    s["speed_rpm"] = 60000.0
    s["direction"] = 1
    s["err_mm"] = 1.5
    s["latency_ms"] = 0.25
    s["t_s"], s["ticks"] = 2.0, 2000
    info = v.show()
    np.testing.assert_array_equal(sc.tool_pos_mm, (8.0, 6.0, 9.0))
    np.testing.assert_array_equal(sc.marker_pos_mm, (9.0, 6.5, 10.0))
    assert info["force_n"] == pytest.approx(0.5) and info["haptic_hz"] == 1000.0
    assert info["drill"] and info["burr"] == "fake" and "message" not in info
    text = sc.hud_text
    assert "following: instructor at test" in text and "tracking error: 1.5 mm" in text
    assert "latency: 0.25 ms" in text and "drill  ON" in text
    s["lost"] = 1
    v.show()
    # the words explained where they are shown
    assert last_message(sc.hud_text) == "LINK LOST - " + \
        GLOSSARY["link lost"].split(": ", 1)[1], sc.hud_text
    s["done"] = 1
    v.show()
    assert last_message(sc.hud_text).startswith("LINK LOST: the session is over")
    # the picture: the instructor's tool and the green hand are drawn
    sc.render()
    img = sc.image()
    green = (img[..., 1].astype(int) - img[..., 0] > 40) & (img[..., 1] > 90)
    assert green.sum() > 20


@pytest.mark.slow
def test_cli_playback_window_offscreen(gl_info, demo_file, tmp_path, capsys):
    from bonesim.cli.main import main
    from bonesim.session.reader import read_session

    n_rem = len(read_session(demo_file).removals["t_s"])
    shot = tmp_path / "trainee.png"
    rc = main(["tutor", "playback", str(demo_file), "--offscreen", "--speed", "4",
               "--screenshot", str(shot), "--size", "320", "240", "--json"])
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    w = s["window"]
    # the window ran until the servo ended and drew every recorded removal
    assert w["frames"] > 1 and w["removed"] == n_rem and w["resets"] == 1
    assert last_message(w["hud"]).startswith("PLAYBACK ENDED")
    assert s["done"] and s["link_lost"] and s["ticks"] > 1000
    assert shot.stat().st_size > 1000
