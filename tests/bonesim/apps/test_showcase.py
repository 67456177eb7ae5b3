"""The headless main job (bonesim.apps.showcase): the plan in simulated time."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bonesim.cli.main import main
from bonesim.io.loading import load_model
from bonesim.apps.showcase import Showcase, run_showcase
from bonesim.io.toolpath import demo_trajectory

SMALL = (160, 120)


@pytest.fixture(scope="module")
def first_cuts():
    """The demo plan from its start to 8 s after the drill starts (it
    plunges through the cortex first)."""
    model = load_model("phantom", "cutting-5mm")
    traj = demo_trajectory(model.case, "cutting-5mm")
    t_on = traj.t_s[np.flatnonzero(traj.drill)[0]]
    return traj.at_times(traj.t_s[traj.t_s <= t_on + 8.0])


def _drill(traj, frame_times):
    with Showcase("phantom", "cutting-5mm", trajectory=traj, size=SMALL,
                  monitor=False) as sh:
        for t in frame_times:
            sh.advance(t)
        return sh.summary(), sh.state.grid.density.copy(), sh.dust.totals_q()


def test_frames_follow_the_simulation(first_cuts):
    """How often frames are drawn does not change what is drilled (the
    headless run's result does not depend on the machine's speed)."""
    end = float(first_cuts.t_s[-1])
    few, dens_few, dust_few = _drill(first_cuts, [end])
    many, dens_many, dust_many = _drill(first_cuts, np.linspace(0.0, end, 9))
    assert few["voxels_removed"] > 100 and few["injuries"] == []
    assert few["steps"] == many["steps"] == len(first_cuts.resample(1000.0).t_s)
    assert few["voxels_removed"] == many["voxels_removed"]
    np.testing.assert_array_equal(dens_few, dens_many)
    # every removed voxel became dust (mass is conserved whatever the frames)
    assert dust_few[1] == dust_many[1] > 0


def test_main_job_rinses_writes_video_and_picture(tmp_path):
    """The first minute of the plan: the suction-irrigator takes the dust,
    the margin holds at native resolution, video and picture are written."""
    video, picture = tmp_path / "run.mp4", tmp_path / "run.png"
    out = run_showcase("phantom", "cutting-5mm", video=video, picture=picture,
                       size=(320, 240), video_s=2.0, fps=5.0, seconds=60.0)
    assert out["simulated_s"] == pytest.approx(60.0, abs=0.01)
    assert out["frames"] == 10 and out["speedup"] == pytest.approx(30.0)
    assert out["voxels_removed"] > 3000 and out["injuries"] == []
    assert set(out["removed_by_structure"]) == {"bone"}
    assert out["min_clearance_mm"] >= 1.0 - 1e-3
    assert out["min_clearance_structure"] in {"sigmoid_sinus", "posterior_fossa_dura",
                                              "middle_fossa_dura", "facial_nerve",
                                              "chorda_tympani", "labyrinth", "ossicles"}
    # much of the dust made went into the suction already (44% since the plan
    # also drills the narrow lobes of each layer, where the suction arrives
    # later; 54% before; none without the suction-irrigator)
    made = out["dust_cells"] + out["dust_suctioned_cells"]
    assert out["dust_suctioned_cells"] > 0.4 * made
    assert video.stat().st_size > 10_000 and picture.stat().st_size > 10_000


def test_headless_run_command(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shot = tmp_path / "end.png"
    assert main(["run", "--offscreen", "--seconds", "2", "--size",
                 "160", "120", "--screenshot", str(shot), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["simulated_s"] == pytest.approx(2.0, abs=0.01) and "video" not in out
    assert shot.stat().st_size > 1000
    assert list(tmp_path.iterdir()) == [shot]     # asked for a picture: no video
    # the final product, item by item (two seconds of the plan: little done)
    a = out["assessment"]
    assert a["checklist"][0].startswith(f"final product: {a['total']} of {a['max_total']}")
    assert len(a["checklist"]) == 1 + len(a["items"]) and a["total"] < a["max_total"]
    assert main(["run", "--offscreen", "--record"]) != 0
    assert "[--record]: --record needs the live simulator" in capsys.readouterr().err
    assert main(["run", "--offscreen", "--frames", "2", "--video", "x.mp4"]) != 0
    assert "[--video]: --video is the headless main job's" in capsys.readouterr().err


def test_headless_run_summary_names_structures(monkeypatch, capsys):
    """The text summary of the main job: clinical names, and the closest
    approach says to what."""
    import bonesim.apps.showcase as S

    def fake(*a, **kw):
        return {"case": "phantom", "burr": "cutting-5mm", "simulated_s": 240.0, "steps": 9,
                "wall_s": 60.0, "voxels_removed": 5, "removed_by_structure": {"bone": 5},
                "injuries": ["chorda_tympani"], "min_clearance_mm": 1.004,
                "min_clearance_structure": "sigmoid_sinus", "picture": "x.png"}

    asked = []
    monkeypatch.setattr(S, "run_showcase", lambda *a, **kw: asked.append(kw) or fake())
    assert main(["run", "--offscreen", "--video", "none"]) == 0
    out = capsys.readouterr().out
    assert "removed 5 voxels (Bone 5); injuries: Chorda tympani" in out
    assert "closest approach: 1.00 mm to the Sigmoid sinus" in out
    # the plain main job writes its time-lapse; a picture asked for comes alone
    for argv, video in ((["run", "--offscreen"], "bonesim-run.mp4"),
                        (["run", "--offscreen", "--screenshot", "a.png"], None),
                        (["run", "--offscreen", "--screenshot", "a.png", "--video", "b.mp4"],
                         "b.mp4")):
        assert main(argv) == 0
        assert asked[-1]["video"] == video

    def fake_assessed(*a, assess=None, **kw):
        out = fake()
        out["assessment"] = {"checklist": ["final product: 3 of 28 (14 items scored)",
                                           "  [0/2]  Antrum opened (...). Deepen."]}
        assert assess is not None
        return out

    monkeypatch.setattr(S, "run_showcase", fake_assessed)
    assert main(["run", "--offscreen", "--video", "none"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-2:] == ["final product: 3 of 28 (14 items scored)",
                        "  [0/2]  Antrum opened (...). Deepen."]


def test_bad_seconds():
    with pytest.raises(ValueError, match="seconds must be positive"):
        run_showcase(seconds=0.0, video=None, picture=None)
