"""Synthetic cohorts: reproducible participants and runs, behaviour that
differs by group the way the metrics look for, and the files a study needs."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.io.loading import load_model
from bonesim.session.reader import read_session
from metrics.synth import (PARTICIPANTS_CSV, SCORE_RANGE, ExpertModel, NoviceModel,
                           draw_participants, expert_trajectory, novice_trajectory,
                           synth_cohort)

#: Short runs keep the tests quick; the behaviours show within them.
RUN_S = 20.0


@pytest.fixture(scope="module")
def models():
    return {"expert": load_model("phantom", ExpertModel().burr),
            "novice": load_model("phantom", NoviceModel().burr)}


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    out = tmp_path_factory.mktemp("cohort")
    return out, synth_cohort(out, 2, 2, seed=5, duration_s=RUN_S)


def test_participants_are_reproducible_and_scored_by_group():
    a = draw_participants(4, 5, seed=11)
    assert a == draw_participants(4, 5, seed=11)
    assert a != draw_participants(4, 5, seed=12)
    assert [p.id for p in a] == ["E01", "E02", "E03", "E04", "N01", "N02", "N03", "N04", "N05"]
    assert all(SCORE_RANGE[0] <= p.instructor_score <= SCORE_RANGE[1] for p in a)
    big = draw_participants(200, 200, seed=1)
    ex = np.mean([p.instructor_score for p in big if p.group == "expert"])
    no = np.mean([p.instructor_score for p in big if p.group == "novice"])
    assert ex - no > 1.2                      # the reference study's gap, roughly
    with pytest.raises(ValueError, match="at least one run"):
        draw_participants(0, 0)
    with pytest.raises(ValueError, match="novices >= 0"):
        draw_participants(2, -1)


def test_trajectories_are_reproducible_and_keep_their_margins(models):
    e, n = [p for p in draw_participants(1, 1, seed=2)]
    me, mn = models["expert"], models["novice"]
    t1 = expert_trajectory(me.case, me.clearance, e, duration_s=RUN_S)
    t2 = expert_trajectory(me.case, me.clearance, e, duration_s=RUN_S)
    np.testing.assert_array_equal(t1.pos_mm, t2.pos_mm)
    np.testing.assert_array_equal(t1.t_s, t2.t_s)
    assert t1.end_s <= RUN_S
    n1 = novice_trajectory(mn.case, mn.grid, mn.clearance, n, duration_s=RUN_S)
    n2 = novice_trajectory(mn.case, mn.grid, mn.clearance, n, duration_s=RUN_S)
    np.testing.assert_array_equal(n1.pos_mm, n2.pos_mm)
    # the expert's burr keeps at least half its (noisy, >= 0.5 mm) margin from
    # every structure that is not bone; the novice comes much closer
    danger = [k for k, st in enumerate(me.case.structures, start=1) if st.kind != "bone"]
    g = me.clearance.group_mask([danger])
    gap_e = me.clearance.distances(t1.pos_mm[t1.drill], g)[:, 0] - me.burr.radius_mm
    gap_n = mn.clearance.distances(n1.pos_mm[n1.drill], g)[:, 0] - mn.burr.radius_mm
    assert gap_e.min() > 0.25 and gap_n.min() < gap_e.min()


def test_an_experts_run_plans_only_what_it_drills(models, monkeypatch):
    """The expert's plan is made only as far as the run reaches
    (``until_s``): the trajectory is the one cut from the whole plan."""
    import bonesim.io.toolpath as toolpath

    (e,) = draw_participants(1, 0, seed=4)
    me = models["expert"]
    short = expert_trajectory(me.case, me.clearance, e, duration_s=6.0, grid=me.grid)
    whole_plan = toolpath.plan_mastoidectomy
    monkeypatch.setattr(toolpath, "plan_mastoidectomy",
                        lambda *a, until_s=None, **k: whole_plan(*a, **k))
    whole = expert_trajectory(me.case, me.clearance, e, duration_s=6.0, grid=me.grid)
    for f in ("t_s", "pos_mm", "axis", "drill", "speed_rpm", "burr", "suction"):
        np.testing.assert_array_equal(getattr(short, f), getattr(whole, f), err_msg=f)


def test_the_expert_slows_down_near_structures(models):
    """The feed of a drilling step falls with the gap to the structures."""
    e = draw_participants(1, 0, seed=3)[0]
    m = models["expert"]
    t = expert_trajectory(m.case, m.clearance, e)
    danger = [k for k, st in enumerate(m.case.structures, start=1) if st.kind != "bone"]
    gap = m.clearance.distances(t.pos_mm, m.clearance.group_mask([danger]))[:, 0]
    step = np.linalg.norm(np.diff(t.pos_mm, axis=0), axis=1)
    speed = step / np.diff(t.t_s)
    cut = t.drill[1:] & (step > 1e-6)
    near = cut & (gap[1:] < np.percentile(gap[1:][cut], 10))
    far = cut & (gap[1:] > np.percentile(gap[1:][cut], 90))
    assert np.median(speed[near]) < 0.7 * np.median(speed[far])


def test_a_cohort_is_recorded_with_its_participants_table(cohort, models):
    out, paths = cohort
    assert [p.name for p in paths] == ["E01.h5", "E02.h5", "N01.h5", "N02.h5"]
    rows = list(csv.DictReader(open(out / PARTICIPANTS_CSV)))
    assert [r["id"] for r in rows] == ["E01", "E02", "N01", "N02"]
    assert [r["group"] for r in rows] == ["expert"] * 2 + ["novice"] * 2
    assert "synthetic" in (out / "README.txt").read_text().lower()
    vis = {}
    for p in paths:
        s = read_session(p)
        assert s.header["participant"] == p.stem and s.header["group"] == ""
        assert "synthetic" in s.header["notes"]
        assert s.samples["t_s"][-1] <= RUN_S + 1e-9
        rem = s.tissue["kind"] == events.REMOVED
        # the runs drill bone (an expert spends its first 20 s on the planned
        # cortical outline, between rinses: a few dozen voxels)
        assert rem.sum() > 20
        vis[p.stem] = float((s.tissue["visible"][rem] == 1).mean())
    # the expert keeps the burr in view; the novice undercuts
    assert min(vis["E01"], vis["E02"]) > max(vis["N01"], vis["N02"])
    # the same seed records the same runs
    again = synth_cohort(out / "again", 2, 2, seed=5, duration_s=RUN_S)
    for a, b in zip(paths, again):
        sa, sb = read_session(a), read_session(b)
        np.testing.assert_array_equal(sa.tissue["ijk"], sb.tissue["ijk"])
        np.testing.assert_array_equal(sa.samples["force_n"], sb.samples["force_n"])


def test_a_folder_with_sessions_is_refused(cohort):
    out, _ = cohort
    with pytest.raises(BonesimError, match="already holds session files"):
        synth_cohort(out, 1, 1, duration_s=1.0)
    with pytest.raises(ValueError, match="duration_s"):
        synth_cohort(out / "new", 1, 1, duration_s=0.0)


def test_burr_stages_change_with_the_drill_resting():
    from metrics.synth import _burr_stages

    drill = np.array([0, 1, 1, 0, 0, 1, 1, 1, 0, 1, 1, 0], bool)
    gap = np.array([9, 9, 9, 9, 9, 1, 1, 9, 9, 9, 9, 9], float)
    assert _burr_stages(drill, gap, 2.0).tolist() == [0, 0, 0, 1, 1, 1, 1, 1, 0, 0, 0, 0]
    assert _burr_stages(drill, gap, 0.5).tolist() == [0] * 12
    assert _burr_stages(drill, gap, 9.0).tolist() == [1] * 12
    b = _burr_stages(drill, gap, 2.0)
    changes = np.flatnonzero(np.diff(b.astype(int))) + 1
    assert not drill[changes].any()                     # never while drilling


def test_the_expert_takes_the_fine_burr_for_the_deep_passes(models, tmp_path):
    """The passes near the structures (the deep layers) use the smaller
    diamond burr at its own speed, the early ones the large cutting burr;
    recorded, the change is a burr change in the session, and the run
    replays bit for bit."""
    from bonesim.io.burrs import load_burr
    from bonesim.session.header import make_header
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.replay import verify

    e = draw_participants(1, 0, seed=3)[0]
    m = models["expert"]
    em = ExpertModel()
    t = expert_trajectory(m.case, m.clearance, e)
    danger = [k for k, st in enumerate(m.case.structures, start=1) if st.kind != "bone"]
    gap = m.clearance.distances(t.pos_mm, m.clearance.group_mask([danger]))[:, 0] \
        - m.burr.radius_mm
    assert t.burr[t.drill][0] == 0 and t.burr[t.drill][-1] == 1      # large first, fine last
    # the fine burr works nearer the structures (the plan's drilling samples
    # include its moves through air between strokes: compare the near tenth)
    assert np.percentile(gap[t.drill & (t.burr == 1)], 10) < \
        np.percentile(gap[t.drill & (t.burr == 0)], 10)
    fine = load_burr(em.fine_burr)
    assert fine.diameter_mm < m.burr.diameter_mm
    assert np.all(t.speed_rpm[t.burr == 1] == fine.default_speed_rpm)
    # record two seconds around the change
    q = int(np.flatnonzero(np.diff(t.burr.astype(int)))[0]) + 1
    cut = t.at_times(t.t_s[(t.t_s >= t.t_s[q] - 1.0) & (t.t_s <= t.t_s[q] + 1.0)])
    while not cut.drill[cut.burr == 1].any():           # reach into the fine pass
        cut = t.at_times(t.t_s[(t.t_s >= cut.t_s[0]) & (t.t_s <= cut.end_s + 1.0)])
    path = tmp_path / "change.h5"
    run_trajectory(m, cut, surface=False, record=path, burrs=[fine],
                   header=make_header(m, [fine], input_device="scripted"))
    s = read_session(path)
    assert [b["name"] for b in s.header["burrs"]] == ["cutting-5mm", em.fine_burr]
    assert s.tissue["n"][s.tissue["kind"] == events.BURR].tolist() == [1]
    assert set(np.unique(s.samples["burr"]).tolist()) == {0, 1}
    assert verify(s)["ok"]


def test_sessions_learning_and_the_recorded_parameters(tmp_path):
    import json

    from metrics.synth import Learning, load_behaviours, session_participant

    e, n, learn = load_behaviours()
    assert e.near_share > 0 and n.aim_share > 0 and learn.novice_per_session > 0
    p = draw_participants(0, 1, seed=1)[0]
    s1, s3 = session_participant(p, 1, learn), session_participant(p, 3, learn)
    assert s1 == p and s3.skill == pytest.approx(p.skill + 2 * learn.novice_per_session)
    assert s3.seed != p.seed and s3.instructor_score >= p.instructor_score
    assert session_participant(p, 3, Learning(novice_per_session=0.0)).skill == p.skill
    from metrics.synth import BEHAVIOURS_FILE

    paths = synth_cohort(tmp_path, 0, 1, seed=4, duration_s=2.0, sessions=2,
                         behaviours=BEHAVIOURS_FILE)
    assert [q.name for q in paths] == ["N01_s1.h5", "N01_s2.h5"]
    rows = list(csv.DictReader(open(tmp_path / PARTICIPANTS_CSV)))
    assert [(r["id"], r["session"], r["file"]) for r in rows] == \
        [("N01", "1", "N01_s1.h5"), ("N01", "2", "N01_s2.h5")]
    rec = json.loads((tmp_path / "synthesis.json").read_text())
    assert rec["seed"] == 4 and rec["sessions"] == 2 and rec["novice"]["aim_share"] == n.aim_share
    bad = tmp_path / "b.toml"
    bad.write_text("[novice]\nwings = 2\n")
    with pytest.raises(BonesimError, match=r"b\.toml: \[novice\] 'wings'"):
        load_behaviours(bad)


def test_skill_lightens_the_novices_plunge(models):
    """With the shipped behaviours a skilled novice plunges slower (toward the
    experts' light touch), so force and speed near the nerves can improve over
    sessions."""
    from dataclasses import replace

    from metrics.synth import load_behaviours

    _, novice, _ = load_behaviours()
    assert novice.plunge_learning > NoviceModel().plunge_learning
    mn = models["novice"]
    p = draw_participants(0, 1, seed=3)[0]

    def slow_feed(skill, model):
        t = novice_trajectory(mn.case, mn.grid, mn.clearance, replace(p, skill=skill),
                              model, duration_s=RUN_S)
        v = np.linalg.norm(np.diff(t.pos_mm, axis=0), axis=1) / np.diff(t.t_s)
        on = t.drill[1:].astype(bool) & (v > 1e-6)
        return float(np.percentile(v[on], 10))        # the plunges, not the sweeps

    assert slow_feed(2.0, novice) < 0.5 * slow_feed(-0.5, novice)
    # the parameter does it: the same skilled novice at the classes' default
    # learning plunges more than twice as fast
    old = replace(novice, plunge_learning=NoviceModel().plunge_learning,
                  min_plunge_mm_s=NoviceModel().min_plunge_mm_s)
    assert slow_feed(2.0, old) > 2.0 * slow_feed(2.0, novice)
