"""``bonesim cohort synth`` from the command line."""
from __future__ import annotations

import json

import numpy as np

from bonesim.cli.main import main


def test_cohort_synth_writes_a_cohort_and_says_so(tmp_path, capsys):
    out = tmp_path / "study"
    assert main(["cohort", "synth", "--experts", "1", "--novices", "1", "--out", str(out),
                 "--duration", "3", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["synthetic"] is True and len(res["sessions"]) == 2
    assert (out / "participants.csv").exists()
    # a second time into the same folder: one clear line, exit status 2
    assert main(["cohort", "synth", "--experts", "1", "--novices", "0", "--out", str(out),
                 "--duration", "3"]) == 2
    err = capsys.readouterr().err
    assert "already holds session files" in err and len(err.strip().splitlines()) == 1
    assert main(["cohort", "synth", "--experts", "0", "--novices", "0", "--out",
                 str(tmp_path / "none")]) == 2
    assert "at least one run" in capsys.readouterr().err


def test_metrics_run_prints_a_summary_and_json(tmp_path, capsys):
    from metrics.synth import synth_cohort

    e, n = synth_cohort(tmp_path / "c", 1, 1, seed=1, duration_s=5.0)
    assert main(["metrics", "run", str(n), "--expert", str(e)]) == 0
    out = capsys.readouterr().out
    assert "visibility:" in out and "final product vs 1 expert run(s)" in out
    # structures by their clinical names in the text (JSON keeps the code names)
    assert "forces near the Chorda tympani:" in out and "exposure Sigmoid sinus:" in out
    assert main(["metrics", "run", str(n), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["run"]["participant"] == "N01" and "final_product" not in res
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not a session")
    assert main(["metrics", "run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and len(err.strip().splitlines()) == 1


def test_metrics_limits_learns_from_the_experts_and_writes_a_file_the_window_reads(
        tmp_path, capsys):
    from bonesim.physics.force_limits import load_limits
    from metrics.forces import force_vs_distance, learn_limits
    from bonesim.session.reader import read_session
    from metrics.synth import synth_cohort

    paths = synth_cohort(tmp_path / "c", 2, 1, seed=2, duration_s=6.0)
    out = tmp_path / "limits.toml"
    # synthetic runs record no group: the participants table says who is an expert
    assert main(["metrics", "limits", str(tmp_path / "c"), "--out", str(out), "--json"]) == 2
    assert "no expert run" in capsys.readouterr().err
    assert main(["metrics", "limits", str(tmp_path / "c"), "--out", str(out), "--json",
                 "--participants", str(tmp_path / "c" / "participants.csv")]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["experts"] == 2 and res["structure"] == "chorda_tympani"
    lim = load_limits(out)
    s = [read_session(p) for p in paths[:2]]
    model = s[0].load_model()
    want = learn_limits([force_vs_distance(x, model=model) for x in s])
    assert np.array_equal(lim.force_n, want.force_n, equal_nan=True)
    assert np.array_equal(lim.speed_rpm, want.speed_rpm, equal_nan=True)
    # the experts' closest approach goes to the window too (one rule, live and offline)
    assert lim.closest_mm == want.closest_mm and res["closest_mm"] == want.closest_mm
    assert [p.rsplit("/", 1)[-1] for p in lim.source] == [p.name for p in paths[:2]]
    # the participants table decides who is an expert: here nobody is
    csv = tmp_path / "p.csv"
    csv.write_text("id,group,instructor_score\nE01,novice,\nE02,novice,\nN01,novice,\n")
    assert main(["metrics", "limits", str(tmp_path / "c"), "--participants", str(csv),
                 "--out", str(tmp_path / "none.toml")]) == 2
    assert "no expert run" in capsys.readouterr().err


def test_metrics_view_writes_a_png_or_opens_a_window(tmp_path, capsys, xdisplay):
    import os
    import subprocess
    import sys
    from pathlib import Path

    from bonesim.render.imagecmp import read_png
    from metrics.synth import synth_cohort

    (n,) = synth_cohort(tmp_path / "c", 0, 1, seed=3, duration_s=5.0)
    png = tmp_path / "v.png"
    assert main(["metrics", "view", str(n), "--png", str(png), "--size", "400", "300",
                 "--structure", "facial_nerve"]) == 0
    assert read_png(png).shape[:2] == (300, 400)
    assert main(["metrics", "view", str(n), "--png", str(png), "--structure", "spleen"]) == 2
    assert "unknown ['spleen']" in capsys.readouterr().err
    # with a display: the window, closed after a few frames
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "DISPLAY": xdisplay,
           "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, "-m", "bonesim.cli", "metrics", "view", str(n),
                        "--frames", "5", "--size", "320", "240"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / "visibility.png").exists()          # it showed, wrote nothing


def test_metrics_export_writes_the_volume_and_the_rows(tmp_path, capsys):
    import nrrd

    from metrics.synth import synth_cohort

    (n,) = synth_cohort(tmp_path / "c", 0, 1, seed=5, duration_s=3.0)
    assert main(["metrics", "export", str(n), "--out", str(tmp_path / "x"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["provenance"]["command"].startswith("bonesim ")
    assert res["provenance"]["session_file"] == str(n)
    hdr = nrrd.read_header(res["visibility"])
    assert "bonesim_provenance" in hdr
    assert main(["metrics", "export", str(tmp_path / "missing.h5"), "--out",
                 str(tmp_path / "y")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
