"""Instructor ratings (metrics.raters): the file format, between-rater ICC on
Shrout & Fleiss' worked example, and the simulator against the raters on
Bland & Altman's worked example."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bonesim.errors import BonesimError
from metrics.agreement import icc
from metrics.raters import instructor_agreement, read_ratings
from tests.metrics.test_agreement import MINI, SHROUT_FLEISS, WRIGHT


def _write(path, rows, head="participant,session,rater,score"):
    path.write_text(head + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


def _shrout_fleiss_file(path):
    """Shrout & Fleiss' 6 targets x 4 judges as 6 participants' first
    session scored by 4 instructors (ICC(2,1) published as .29)."""
    rows = [(f"P{q + 1}", 1, f"judge{j + 1}", v) for q, r in enumerate(SHROUT_FLEISS)
            for j, v in enumerate(r)]
    return _write(path, rows)


def test_between_rater_icc_of_shrout_and_fleiss(tmp_path):
    people = {f"P{q}": {"group": "novice"} for q in range(1, 7)}
    r = read_ratings(_shrout_fleiss_file(tmp_path / "r.csv"), people)
    assert list(r.columns) == ["participant", "session", "rater", "score"] and len(r) == 24
    got = instructor_agreement(r, pd.DataFrame(columns=["participant", "session"]))
    br = got["between_raters"]
    assert br["raters"] == ["judge1", "judge2", "judge3", "judge4"] and br["runs"] == 6
    assert round(br["icc"]["icc2_1"], 2) == 0.29           # the published value
    assert br["icc"]["icc2_1"] == pytest.approx(icc(SHROUT_FLEISS)["icc2_1"], abs=1e-12)
    # no simulator column: said, not a crash
    assert "no column 'assess_total'" in got["against"]["note"]
    # a run one rater did not score is left out and counted
    r2 = r[~((r["participant"] == "P6") & (r["rater"] == "judge2"))]
    br2 = instructor_agreement(r2, pd.DataFrame(columns=["participant", "session"]))
    assert br2["between_raters"]["runs"] == 5 and br2["between_raters"]["runs_left_out"] == 1
    assert br2["between_raters"]["icc"]["icc2_1"] == pytest.approx(
        icc(SHROUT_FLEISS[:5])["icc2_1"], abs=1e-12)


def test_simulator_against_instructors_is_bland_and_altmans_example():
    """The simulator's score as the mini Wright meter, two instructors whose
    mean is the Wright meter: the published bias (2.1 l/min, mini minus
    Wright) and the ICC of the two columns; one rated run without a scored
    run is listed."""
    n = len(WRIGHT)
    rows = []
    for q, w in enumerate(WRIGHT):
        rows += [(f"P{q}", 2.0, "A", w - 3.0), (f"P{q}", 2.0, "B", w + 3.0)]
    rows.append(("ghost", 1.0, "A", 5.0))
    ratings = pd.DataFrame(rows, columns=["participant", "session", "rater", "score"])
    table = pd.DataFrame({"participant": [f"P{q}" for q in range(n)], "session": [2.0] * n,
                          "assess_total": MINI})
    got = instructor_agreement(ratings, table)["against"]
    assert got["runs"] == n and got["unmatched"] == ["ghost session 1"]
    assert got["bland_altman"]["bias"] == pytest.approx(np.mean(np.subtract(MINI, WRIGHT)))
    assert round(got["bland_altman"]["bias"], 1) == 2.1
    assert got["icc"]["icc2_1"] == pytest.approx(
        icc(np.column_stack([MINI, WRIGHT]))["icc2_1"], abs=1e-12)
    # the raters differ by a constant 6: absolute agreement is below consistency
    br = instructor_agreement(ratings, table)["between_raters"]
    assert br["icc"]["icc2_1"] < br["icc"]["icc3_1"]


@pytest.mark.parametrize("text, needle", [
    ("", "empty; expected a header line participant,session,rater,score"),
    ("participant,session,rater\nP1,1,a\n", "line 1: the columns must be"),
    ("participant,session,rater,score,extra\n", "line 1: the columns must be"),
    ("participant,session,rater,score\nP1,1,a,4\nP1,1,a,5\n",
     "line 3: rater 'a' scored participant 'P1' session 1 already on line 2"),
    ("participant,session,rater,score\nP1,one,a,4\n", "line 2, column 'session': 'one'"),
    ("participant,session,rater,score\nP1,1,a,nan\n", "line 2, column 'score': 'nan' is not"),
    ("participant,session,rater,score\nP1,1,,4\n", "line 2, column 'rater': empty"),
    ("participant,session,rater,score\nP9,1,a,4\n",
     "line 2, column 'participant': 'P9' is not in the participants table"),
    ("participant,session,rater,score\nP1,1,a\n", "line 2: 3 fields, the header has 4"),
    ("participant,session,rater,score\n", "no scores after the header"),
])
def test_a_bad_ratings_file_gives_one_line_naming_it(tmp_path, text, needle):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(BonesimError) as e:
        read_ratings(p, {"P1": {"group": "expert"}})
    msg = str(e.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


def test_binary_and_missing_ratings_files(tmp_path):
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(BonesimError, match="not UTF-8"):
        read_ratings(p)
    with pytest.raises(BonesimError, match="cannot read the ratings"):
        read_ratings(tmp_path / "missing.csv")


def test_cohort_refuses_a_bad_ratings_file_before_scoring(tmp_path, capsys):
    """One line and exit status 2, with no session scored."""
    from bonesim.cli.main import main

    (tmp_path / "p.csv").write_text("id,group,instructor_score\nP1,expert,\n")
    bad = _write(tmp_path / "r.csv", [("P1", 1, "a", "x")])
    assert main(["metrics", "cohort", str(tmp_path), "--participants",
                 str(tmp_path / "p.csv"), "--ratings", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "column 'score'" in err[0]


def test_the_report_and_exports_carry_the_instructor_agreement(tmp_path):
    from metrics.cohort_result import CohortResult
    from metrics.exports import export_cohort
    from metrics.report_design import instructor_section

    r = read_ratings(_shrout_fleiss_file(tmp_path / "r.csv"))
    table = pd.DataFrame({"participant": [f"P{q}" for q in range(1, 7)], "session": 1.0,
                          "assess_total": [6.0, 3.0, 6.5, 4.0, 7.5, 4.5]})
    ins = {"file": "r.csv", "sha256": "ab" * 32, **instructor_agreement(r, table)}
    res = CohortResult(table=table, stats=pd.DataFrame(), instructors=ins)

    class Figs:
        def fig(self, fig, stem, alt):
            return f"<img alt='{alt}'>"

    html = instructor_section(res, Figs())
    assert "between the raters (judge1, judge2, judge3, judge4)" in html
    assert f"{ins['between_raters']['icc']['icc2_1']:.3g}" in html
    assert "Bland-Altman simulator against instructors" in html
    export_cohort(res, tmp_path / "x")
    rec = json.loads((tmp_path / "x" / "provenance.json").read_text())["instructors"]
    assert rec["between_raters"]["icc"]["icc2_1"] == pytest.approx(
        ins["between_raters"]["icc"]["icc2_1"])
    assert "mean" not in rec["against"]["bland_altman"]      # the numbers, not the points
