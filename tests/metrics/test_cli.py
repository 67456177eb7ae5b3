"""``bonesim cohort synth`` from the command line."""
from __future__ import annotations

import json

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
    assert main(["metrics", "run", str(n), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["run"]["participant"] == "N01" and "final_product" not in res
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not a session")
    assert main(["metrics", "run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and len(err.strip().splitlines()) == 1
