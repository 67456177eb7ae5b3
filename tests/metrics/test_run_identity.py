"""A copied recording counts once in a cohort (issue 24: a byte-identical copy
and a truncated copy were scored as extra participants' runs, with no notice)."""
from __future__ import annotations

import shutil

import pytest


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from metrics.synth import PARTICIPANTS_CSV, synth_cohort

    d = tmp_path_factory.mktemp("runs")
    paths = synth_cohort(d, 2, 2, seed=5, duration_s=4.0)
    return d, sorted(paths), d / PARTICIPANTS_CSV


def _copies(d, paths):
    """A byte-identical copy of the first run and a truncated copy of the second."""
    same = d / "zz_same.h5"
    shutil.copyfile(paths[0], same)
    cut = d / "zz_cut.h5"
    data = paths[1].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    return same, cut


def test_copies_are_found_reported_and_left_out(runs, tmp_path):
    from metrics.run_identity import content_hash, distinct_runs, run_hash

    src, paths, _ = runs
    d = tmp_path / "c"
    d.mkdir()
    mine = [d / p.name for p in paths]
    for a, b in zip(paths, mine):
        shutil.copyfile(a, b)
    same, cut = _copies(d, mine)
    kept, notices, copies = distinct_runs(mine + [same, cut])
    assert kept == mine
    assert copies == {str(same): str(mine[0]), str(cut): str(mine[1])}
    assert len(notices) == 2 and all("\n" not in n for n in notices)
    assert "byte-identical copy of" in notices[0] and str(same) in notices[0]
    assert "same run" in notices[1] and str(cut) in notices[1]
    # distinct runs have distinct hashes; a copy shares them
    assert len({run_hash(p) for p in mine}) == len(mine)
    assert content_hash(same) == content_hash(mine[0]) != content_hash(cut)
    assert run_hash(cut) == run_hash(mine[1])
    # the larger file of a run is kept whatever the order
    kept, _, copies = distinct_runs([cut, *mine])
    assert kept == mine and copies == {str(cut): str(mine[1])}


def test_unreadable_files_are_left_to_the_scoring(tmp_path):
    from metrics.run_identity import distinct_runs

    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.write_bytes(b"not a session")
    b.write_bytes(b"another thing")
    kept, notices, _ = distinct_runs([a, b, tmp_path / "missing.h5"])
    assert kept == [a, b, tmp_path / "missing.h5"] and notices == []


def test_the_cohort_counts_a_copied_run_once(runs):
    from metrics.cohort import score_cohort

    d, paths, csv_path = runs
    same, cut = _copies(d, paths)
    try:
        res = score_cohort(d, csv_path, workers=1)
    finally:
        same.unlink()
        cut.unlink()
    assert len(res.table) == len(paths)
    assert set(res.table["file"]) == {str(p) for p in paths}
    assert sum("counted once" in e for e in res.errors) == 2
    assert res.meta["copies"] == {str(same): str(paths[0]), str(cut): str(paths[1])}
