"""Scoring a cohort on Dask (metrics.cohort, ``bonesim metrics cohort``): on a
synthetic cohort of 3 + 3 short runs, the table matches the direct per-run
functions and a serial leave-one-participant-out Naive Bayes; broken inputs
each give one line and the rest is scored; an existing cluster is used and
left running."""
from __future__ import annotations

import csv
import json
import os
import shutil

import numpy as np
import pytest

from metrics.cohort import metric_columns
from metrics.cohort_result import METRIC_COLUMNS, RUN_COLUMNS


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    from metrics.synth import PARTICIPANTS_CSV, synth_cohort

    d = tmp_path_factory.mktemp("cohort")
    paths = synth_cohort(d, 3, 3, seed=3, duration_s=8.0)
    return d, paths, d / PARTICIPANTS_CSV


@pytest.fixture(scope="module")
def cluster():
    """A running one-worker cluster that tests pass by address (a user's
    existing cluster: each start of one costs a worker's imports and models)."""
    from metrics.cohort import local_cluster

    with local_cluster(1) as c:
        yield c


@pytest.fixture(scope="module")
def clean(cohort):
    from metrics.cohort import score_cohort

    d, _, csv_path = cohort
    seen = []
    res = score_cohort(d, csv_path, workers=2, progress=lambda done, n: seen.append((done, n)))
    return res, seen


def _edit_header(path, **change):
    import h5py

    with h5py.File(path, "r+") as f:
        h = json.loads(f.attrs["header"])
        for k, v in change.items():
            if k == "case":
                h["case"]["name"] = v
            else:
                h[k] = v
        f.attrs["header"] = json.dumps(h)
        if "header_sha256" in f.attrs:       # an edit made on purpose: signed again
            from bonesim.session.header import header_sha256

            f.attrs["header_sha256"] = header_sha256(f.attrs["format"], f.attrs["schema"],
                                                     f.attrs["header"])


def test_table_has_a_row_per_file_and_matches_the_direct_functions(cohort, clean):
    from bonesim.session.reader import read_session
    from metrics.regions import loo_scores, region_run
    from metrics.visibility import visible_fraction

    _, paths, csv_path = cohort
    res, seen = clean
    tb = res.table
    assert list(tb.columns) == [*RUN_COLUMNS, *metric_columns()]
    assert np.isfinite(tb["assess_total"].astype(float)).all()   # the final product joins
    assert list(tb["file"]) == sorted(str(p) for p in paths)
    assert (tb["error"] == "").all() and res.errors == []
    assert seen[-1] == (6, 6) and [s[0] for s in seen] == list(range(1, 7))
    with open(csv_path) as f:
        groups = {r["id"]: r["group"] for r in csv.DictReader(f)}
    assert list(tb["group"]) == [groups[p] for p in tb["participant"]]
    sessions = [read_session(f) for f in tb["file"]]
    serial = loo_scores([region_run(s, group=groups[s.header["participant"]])
                         for s in sessions])
    np.testing.assert_allclose(tb["nb_score"], serial.scores, rtol=1e-12)
    vf = visible_fraction(sessions[0])
    assert tb["visible_fraction"].iloc[0] == pytest.approx(vf, rel=1e-12)
    for f, trained in res.nb_trained_on.items():
        assert f not in trained and len(trained) == 5
    assert set(res.force_tables) == set(tb["file"])
    for name in ("duration_s", "removed_voxels", "visible_fraction", "nb_score",
                 "final_dice", "final_mean_mm", "exceedances"):
        assert np.isfinite(tb[name]).all(), name
    st = res.stats
    assert {"metric", "unit", "better", "expert_n", "novice_mean", "t", "p_t", "u", "p_u",
            "u_method", "d", "d_lo", "d_hi", "rho", "p_rho", "r", "p_r"} <= set(st.columns)
    assert "nb_score" in set(st["metric"])
    assert res.meta["scheduler"] == "LocalCluster" and res.meta["workers"] == 2


def test_broken_inputs_give_one_line_each_on_an_existing_cluster(cohort, cluster,
                                                                tmp_path):
    """Random bytes, a copy cut at half its size (a copy of a run: counted
    once, issue 24), a file of another case, a run whose participant is not
    in the table and a participant with no run: one line each, the rest scored. The cluster passed by address stays up."""
    import pandas as pd
    from distributed import Client

    from metrics.cohort import score_cohort

    _, paths, csv_path = cohort
    for p in paths:
        shutil.copy(p, tmp_path / p.name)
    (tmp_path / "corrupt.h5").write_bytes(np.random.default_rng(0).bytes(4096))
    cut = tmp_path / "cut.h5"
    shutil.copy(paths[3], cut)
    os.truncate(cut, cut.stat().st_size // 2)
    shutil.copy(paths[1], tmp_path / "other_case.h5")
    _edit_header(tmp_path / "other_case.h5", case="otherbone")
    shutil.copy(paths[2], tmp_path / "stranger.h5")
    _edit_header(tmp_path / "stranger.h5", participant="X99")
    table = tmp_path / "people.csv"
    table.write_text(csv_path.read_text() + "E99,expert,4.0\n")

    res = score_cohort(str(tmp_path / "*.h5"), table, scheduler=cluster.scheduler_address)
    with Client(cluster.scheduler_address) as c:            # still running
        assert c.submit(lambda: 41 + 1).result() == 42
    tb = res.table.set_index(res.table["file"].map(lambda f: os.path.basename(f)))
    assert len(tb) == len(paths) + 3                        # the cut copy left out
    assert res.meta["scheduler"] == cluster.scheduler_address
    err = res.errors

    def one(*words):
        return [e for e in err if all(w in e for w in words)]

    assert len(one("corrupt.h5", "not an HDF5 file")) == 1
    assert len(one("cut.h5", "a copy of the same run", paths[3].name, "counted once")) == 1
    assert len(one("other_case.h5", "case 'otherbone' is not the cohort's case 'phantom'")) == 1
    assert len(one("stranger.h5", "'X99'", "not in")) == 1
    assert len(one("'E99'", "has no run")) == 1
    assert len(err) == 5, err
    assert all("\n" not in e for e in err)
    for f in ("corrupt.h5", "other_case.h5"):
        assert tb.loc[f, "error"] and np.isnan(tb.loc[f, "visible_fraction"])
    assert "cut.h5" not in tb.index
    s = tb.loc["stranger.h5"]
    assert s["error"] == "" and pd.isna(s["group"]) and np.isfinite(s["visible_fraction"])
    # no group: scored by a model of every labelled run, out of the statistics
    assert np.isfinite(s["nb_score"]) and np.isfinite(s["nb_score_per_voxel"])
    labelled = [f for f in tb["file"] if tb.loc[os.path.basename(f), "group"] in
                ("expert", "novice")]
    assert sorted(res.nb_trained_on[s["file"]]) == sorted(labelled)
    good = tb.loc[[p.name for p in paths]]
    assert (good["error"] == "").all() and np.isfinite(good["nb_score"]).all()
    assert set(res.stats["expert_n"]) <= {3}


def test_bad_participants_table_names_file_line_and_column(tmp_path):
    from bonesim.errors import BonesimError
    from metrics.cohort import read_participants

    p = tmp_path / "p.csv"
    p.write_text("id,group\nA,expert\n")
    with pytest.raises(BonesimError, match=r"p\.csv: line 1: column 'instructor_score'"):
        read_participants(p)
    p.write_text("id,group,instructor_score\nA,expert,3\nB,resident,2\n")
    with pytest.raises(BonesimError, match=r"line 3, column 'group': 'resident'"):
        read_participants(p)
    p.write_text("id,group,instructor_score\nA,expert,good\n")
    with pytest.raises(BonesimError, match=r"line 2, column 'instructor_score': 'good'"):
        read_participants(p)
    p.write_text("id,group,instructor_score\nA,Expert,\nB,novice,2.5\n")
    out = read_participants(p)
    assert out["A"]["group"] == "expert" and np.isnan(out["A"]["instructor_score"])
    assert out["B"]["instructor_score"] == 2.5


def test_cli_writes_parquet_and_prints_json(cohort, cluster, tmp_path, capsys):
    import pandas as pd

    from bonesim.cli.main import main

    d, _, csv_path = cohort
    out = tmp_path / "x.parquet"
    rc = main(["metrics", "cohort", str(d), "--participants", str(csv_path), "--out",
               str(out), "--scheduler", cluster.scheduler_address, "--json"])
    assert rc == 0
    cap = capsys.readouterr()
    summary = json.loads(cap.out)
    assert summary["runs"] == 6 and summary["scored"] == 6 and summary["failed"] == 0
    assert summary["table"] == str(out)
    assert any(s["metric"] == "nb_score" for s in summary["significant"])
    tb = pd.read_parquet(out)
    assert list(tb.columns) == [*RUN_COLUMNS, *metric_columns()] and len(tb) == 6
    assert "scoring" in cap.err


def test_cli_text_summary_failed_runs_and_missing_report(cohort, tmp_path, capsys,
                                                         monkeypatch):
    import sys

    import pandas as pd

    from bonesim.cli.main import main

    _, paths, csv_path = cohort
    for p in paths:
        shutil.copy(p, tmp_path / p.name)
    (tmp_path / "junk.h5").write_bytes(b"not a session at all")
    monkeypatch.setitem(sys.modules, "metrics.report", None)     # import fails
    out = tmp_path / "t.csv"
    rc = main(["metrics", "cohort", str(tmp_path / "*.h5"), "--participants", str(csv_path),
               "--out", str(out), "--report", str(tmp_path / "r.html"), "--workers", "1"])
    assert rc == 0
    cap = capsys.readouterr()
    assert "6 of 7 runs scored (1 failed) on case phantom" in cap.out
    assert "nb_score" in cap.out and "report: metrics.report is not available" in cap.out
    bad = [ln for ln in cap.err.splitlines() if "junk.h5" in ln]
    assert len(bad) == 1 and "not an HDF5 file" in bad[0]
    tb = pd.read_csv(out)
    assert len(tb) == 7 and tb["error"].notna().sum() == 1


def test_a_file_cut_short_is_scored_on_its_readable_part(tmp_path):
    """A run of 30 s cut at 70 % of its size keeps its first samples (the file
    is written in time order, 8,192-row chunks): it is scored on them (no
    error), its damage line travels with it, and the scores are those of the
    readable part (fewer removals than the whole)."""
    from bonesim.session.reader import read_session
    from metrics.cohort import score_file
    from metrics.synth import synth_cohort

    (whole,) = synth_cohort(tmp_path / "run", 0, 1, seed=7, duration_s=30.0)
    cut = tmp_path / "cut.h5"
    shutil.copy(whole, cut)
    os.truncate(cut, int(cut.stat().st_size * 0.7))
    full, part = score_file(whole), score_file(cut)
    assert "error" not in part, part.get("error")
    assert part["damage"] and "cut.h5" in part["damage"] and full["damage"] is None
    s = read_session(cut)
    kept, total = len(s.samples["t_s"]), len(read_session(whole).samples["t_s"])
    assert s.damage is not None and 0 < kept < total
    assert 0 < part["metrics"]["removed_voxels"] < full["metrics"]["removed_voxels"]
    assert part["metrics"]["duration_s"] < full["metrics"]["duration_s"]
    assert np.isfinite(part["metrics"]["visible_fraction"])


def test_cli_exports_with_provenance_and_draws_progress(cohort, cluster, tmp_path, capsys):
    import pandas as pd

    from bonesim.cli.main import main

    d, paths, csv_path = cohort
    ex = tmp_path / "ex"
    assert main(["metrics", "cohort", str(d), "--participants", str(csv_path), "--scheduler",
                 cluster.scheduler_address, "--exports", str(ex), "--report",
                 str(tmp_path / "r.html"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["unit"] == "participant" and summary["stats_s"] >= 0
    assert {"duration_s", "drilled_mm3"} <= set(summary["excluded"])
    auc = summary["naive_bayes_auc"]["nb_score"]
    assert 0 <= auc["ci"][0] <= auc["auc"] <= auc["ci"][1] <= 1
    st = pd.read_csv(ex / "stats.csv")
    assert "duration_s" not in set(st["metric"]) and {"p_t_holm", "p_t_bh"} <= set(st.columns)
    meta = json.loads((ex / "provenance.json").read_text())
    prov = meta["provenance"]
    assert prov["synthesis"]["seed"] == 3 and prov["case"][0]["name"] == "phantom"
    assert len(prov["participants_sha256"]) == 64 and "--exports" in prov["command"]
    page = (tmp_path / "r.html").read_text()
    assert page.index("Design and provenance") < page.index("1. Cohort")
    assert prov["participants_sha256"] in page and "Naive Bayes as a classifier" in page
    png = tmp_path / "p.png"
    assert main(["metrics", "progress", str(d), "--participants", str(csv_path), "--out",
                 str(png), "--workers", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["png"] == str(png) and png.stat().st_size > 10_000
    assert "visible_fraction" in out["metrics"]


def test_row_providers_add_columns_and_a_failing_one_says_so(cohort):
    from bonesim.session.reader import read_session
    from metrics.cohort import metric_columns, score_file

    _, paths, _ = cohort
    good = ("tests.metrics.cohort_fixtures", "extra_row", {"samples_n": ("", 0)})
    bad = ("tests.metrics.cohort_fixtures", "broken_row", {"broken_x": ("", 1)})
    r = score_file(paths[0], providers=(good, bad))
    assert r["extra"]["samples_n"] == len(read_session(paths[0]).samples["t_s"])
    assert np.isnan(r["extra"]["broken_x"])
    assert len(r["warnings"]) == 1 and "provider exploded" in r["warnings"][0]
    cols = metric_columns((good, bad))
    assert list(cols)[-2:] == ["samples_n", "broken_x"] and set(METRIC_COLUMNS) < set(cols)
