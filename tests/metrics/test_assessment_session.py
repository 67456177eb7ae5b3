"""The assessment from recorded runs: ``bonesim assess``, ``bonesim metrics
run``, the rows for the cohort table, and the main job's plan recorded and
scored from the file alone."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bonesim.cli.main import main


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from metrics.synth import synth_cohort

    return synth_cohort(tmp_path_factory.mktemp("assess"), 1, 1, seed=2, duration_s=6.0)


def test_session_equals_the_replayed_tissue(runs):
    """Scored from the file's removals, a run scores as its tissue at the end
    (the engine's state after replaying its samples) does."""
    from bonesim.session.reader import read_session
    from bonesim.session.replay import replay
    from metrics.assessment import assess_grid, assess_session, final_present

    s = read_session(runs[1])
    model = s.load_model()
    a = assess_session(s, model=model)
    state = replay(s, models=s.burr_models())["state"]
    assert np.array_equal(final_present(s, model), state.grid.to_dense()[0] > 0)
    b = assess_grid(model, state.grid)
    assert a.as_dict() == b.as_dict()
    assert a.removed_mm3 > 0.0


def test_assess_command_text_json_png(runs, tmp_path, capsys):
    from bonesim.render.assessment_view import OUTCOME_RGB
    from bonesim.render.imagecmp import read_png
    from metrics.assessment import assess_session

    e, n = runs
    assert main(["assess", str(n)]) == 0
    out = capsys.readouterr().out.splitlines()
    want = assess_session(n)
    assert out[1].startswith(f"final product: {want.total} of {want.max_total}")
    assert len(out) == 2 + len(want.items)
    assert main(["assess", str(n), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["total"] == want.total and [i["score"] for i in got["items"]] == \
        [it.score for it in want.items]
    png = tmp_path / "a.png"
    assert main(["assess", str(e), "--png", str(png), "--size", "480", "360"]) == 0
    assert str(png) in capsys.readouterr().out
    img = read_png(png)
    assert img.shape[:2] == (360, 480)
    # the legend and regions in the outcomes' colours
    ae = assess_session(e)
    for outcome in {it.outcome for it in ae.items if it.score is not None}:
        rgb = np.array(OUTCOME_RGB[outcome])
        close = np.all(np.abs(img[..., :3].astype(int) - rgb) < 40, axis=2)
        assert close.sum() > 20, outcome
    assert main(["assess", str(tmp_path / "missing.h5")]) == 2
    err = capsys.readouterr().err
    assert "missing.h5" in err and len(err.strip().splitlines()) == 1
    assert main(["assess", str(n), "--png", str(png), "--size", "4", "4"]) == 2
    assert "--size" in capsys.readouterr().err


def test_metrics_run_carries_the_checklist(runs, capsys):
    assert main(["metrics", "run", str(runs[0])]) == 0
    out = capsys.readouterr().out
    assert "final product:" in out and "Antrum opened" in out
    assert main(["metrics", "run", str(runs[0]), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["assessment"]["total"] <= res["assessment"]["max_total"] == 28
    assert res["assessment"]["checklist"][0].startswith("final product:")


def test_rows_and_progress(runs, tmp_path):
    from metrics.assessment import (assess_session, assessment_columns, assessment_progress,
                                    assessment_row)

    row = assessment_row(runs[0])
    assert tuple(row) == assessment_columns()
    assert row["assess_total"] == assess_session(runs[0]).total
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    rows = assessment_progress([runs[1], bad, runs[0]])
    assert [r.get("error") is not None for r in rows].count(True) == 1
    ok = [r for r in rows if "error" not in r]
    assert {r["participant"] for r in ok} == {"E01", "N01"}
    assert all(r["session"] == 1 for r in ok)


@pytest.mark.slow
def test_main_job_plan_recorded_scores_full_marks(tmp_path):
    """The main job's plan (cutting then diamond burr), drilled through the
    engine at the haptic rate and recorded, scored from the file alone:
    full marks on every item (the plan performs all of them on the phantom)."""
    from bonesim.io.burrs import load_burr
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import plan_mastoidectomy
    from bonesim.session.header import make_header
    from bonesim.runtime.simulate import run_trajectory
    from metrics.assessment import assess_session

    run = plan_mastoidectomy(load_case("phantom"))
    model = load_model("phantom", run.burrs[0])
    extra = [load_burr(b) for b in run.burrs[1:]]
    path = tmp_path / "plan.h5"
    run_trajectory(model, run.trajectory, surface=False, record=path, burrs=extra,
                   header=make_header(model, extra, input_device="scripted"))
    a = assess_session(path)
    assert {it.name: it.outcome for it in a.items if it.score != 2} == {}
    assert a.total == a.max_total == 28
