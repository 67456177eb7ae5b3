"""The per-run cache of cohort scoring (metrics.run_cache): a second scoring
of an unchanged cohort scores nothing, a changed file is scored again, and
the cached rows equal freshly scored ones."""
from __future__ import annotations

import math

import h5py
import numpy as np
import pandas as pd
import pytest

import metrics.cohort as cohort
from metrics.run_cache import RunCache


def test_keys_follow_content_and_settings_and_bad_entries_are_misses(tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.write_bytes(b"one")
    b.write_bytes(b"one")
    rc = RunCache(tmp_path / "c", {"structure": "x"})
    assert rc.key(a) == rc.key(b)                       # content, not name
    assert RunCache(tmp_path / "c", {"structure": "y"}).key(a) != rc.key(a)
    assert rc.get(a) is None and rc.misses == 1
    res = {"file": str(a), "metrics": {"m": 1.0}, "warnings": [], "damage": None}
    assert rc.put(a, res)
    got = rc.get(b)                                     # same bytes, its own path
    assert got["metrics"] == {"m": 1.0} and got["file"] == str(b) and rc.hits == 1
    # unclean results are not kept
    assert not rc.put(a, {"file": str(a), "error": "x"})
    assert not rc.put(a, {**res, "warnings": ["w"]})
    assert not rc.put(a, {**res, "damage": "salvaged"})
    # a changed file is another key (a fresh cache object hashes it again)
    a.write_bytes(b"two")
    assert RunCache(tmp_path / "c", {"structure": "x"}).get(a) is None
    # a corrupt entry is a miss, and is rewritten
    rc2 = RunCache(tmp_path / "c", {"structure": "x"})
    (tmp_path / "c" / f"{rc2.key(b)}.pkl").write_bytes(b"garbage")
    assert rc2.get(b) is None
    assert rc2.put(b, res) and rc2.get(b)["metrics"] == {"m": 1.0}
    assert not list((tmp_path / "c").glob("*.tmp"))


@pytest.fixture(scope="module")
def small_cohort(tmp_path_factory):
    from metrics.synth import synth_cohort

    folder = tmp_path_factory.mktemp("cached")
    synth_cohort(folder, 2, 2, seed=3, duration_s=4.0)
    return folder


def test_a_second_scoring_reads_the_cache_and_a_changed_file_is_rescored(
        small_cohort, tmp_path, monkeypatch):
    """Runs scored serially (the Dask step replaced by a loop that records
    what it was given): the second call scores nothing and gives the same
    table; after one file changes, only that file is scored."""
    calls = []

    def serial(paths, structure, case, scheduler, workers, progress, close_mm, providers):
        calls.append([p.name for p in paths])
        return ([cohort.score_file(p, structure, case, close_mm, providers) for p in paths],
                "serial", 1)

    monkeypatch.setattr(cohort, "_run_tasks", serial)
    cache = tmp_path / "cache"
    parts = small_cohort / "participants.csv"
    first = cohort.score_cohort(small_cohort, parts, cache=cache)
    assert len(calls[0]) == 4 and first.meta["cached"] == 0
    second = cohort.score_cohort(small_cohort, parts, cache=cache)
    assert len(calls) == 1 and second.meta["cached"] == 4     # nothing scored again
    cols = [c for c in first.table.columns if c != "error"]
    pd.testing.assert_frame_equal(first.table[cols], second.table[cols])
    # one file changes (an attribute added: new bytes, still a valid run)
    f = sorted(small_cohort.glob("*.h5"))[1]
    with h5py.File(f, "r+") as h:
        h.attrs["touched_by_test"] = 1
    third = cohort.score_cohort(small_cohort, parts, cache=cache)
    assert calls[1] == [f.name] and third.meta["cached"] == 3
    a = third.table.set_index("file").loc[str(f), "visible_fraction"]
    b = first.table.set_index("file").loc[str(f), "visible_fraction"]
    assert a == b or (math.isnan(a) and math.isnan(b))
    # without a cache every run is scored
    cohort.score_cohort(small_cohort, parts)
    assert len(calls[2]) == 4


def test_progress_cli_says_how_many_runs_came_from_the_cache(small_cohort, tmp_path,
                                                             monkeypatch, capsys):
    from bonesim.cli.main import main

    def serial(paths, structure, case, scheduler, workers, progress, close_mm, providers):
        return ([cohort.score_file(p, structure, case, close_mm, providers) for p in paths],
                "serial", 1)

    monkeypatch.setattr(cohort, "_run_tasks", serial)
    args = ["metrics", "progress", str(small_cohort), "--participants",
            str(small_cohort / "participants.csv"), "--out", str(tmp_path / "p.png"),
            "--cache", str(tmp_path / "c")]
    assert main(args) == 0
    assert "0 of 4 runs read from the cache" in capsys.readouterr().err
    assert main(args) == 0
    assert "4 of 4 runs read from the cache" in capsys.readouterr().err
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
