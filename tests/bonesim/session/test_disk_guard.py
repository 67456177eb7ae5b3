"""A full disk, for real: the process's file-size limit (``RLIMIT_FSIZE``, set
with ``resource.setrlimit``; Python ignores SIGXFSZ, so a write past it fails
with EFBIG as a write to a full disk fails with ENOSPC). The writer stops,
says what it kept, and the file holds exactly that; nothing raises, nothing
crashes, no zero rows pass as data; compaction that runs out of room leaves
the raw file and no temporary."""
from __future__ import annotations

import contextlib
import errno
import json
import resource
import signal

import numpy as np
import pytest

from bonesim.cli.main import main
from bonesim.errors import EXIT_RECORDING_LOST, BonesimError
from bonesim.session import disk_guard
from bonesim.session.disk_guard import (GuardedFile, SpaceLimits, check_space, estimate_bytes,
                                        headroom_bytes, load_space_limits)
from bonesim.session.writer import SessionWriter, compact_session, compaction_temp, kept_line
from bonesim.session.reader import read_session
from bonesim.session.replay import coverage
from tests.bonesim.session.fault_files import HEADER, write_synthetic

MB = 1 << 20


@contextlib.contextmanager
def file_size_limit(nbytes: int):
    """Files this process writes may not grow past ``nbytes`` (soft limit;
    restored after)."""
    assert signal.getsignal(signal.SIGXFSZ) == signal.SIG_IGN    # Python's default
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


@pytest.fixture
def no_reserve(monkeypatch):
    """Write up to the last byte (no space kept back): the hard failure path."""
    monkeypatch.setattr(disk_guard, "load_space_limits", lambda path=None: SpaceLimits(
        reserve_mb=0.0))


def test_shipped_limits_load():
    lim = load_space_limits()
    assert lim.reserve_mb > 0 and lim.check_every_s > 0 and lim.tissue_rows_per_s > 0
    assert estimate_bytes(60, 1000.0, lim) > estimate_bytes(10, 1000.0, lim) > 0


def test_guarded_file_keeps_the_first_failed_write_and_never_raises(tmp_path):
    p = tmp_path / "g.bin"
    with file_size_limit(10_000):
        g = GuardedFile(p)
        assert headroom_bytes(p) <= 10_000
        g.write(b"a" * 8000)
        assert g.error is None
        g.write(b"b" * 8000)                       # past the limit: EFBIG, kept
        g.write(b"c" * 10)                         # dropped
        assert g.error is not None and g.error.errno == errno.EFBIG
        assert "largest size allowed" in disk_guard.describe_error(g.error)
        g.seek(0)
        assert g.read(4) == b"aaaa"
        g.close()
    assert p.stat().st_size <= 10_000
    with pytest.raises(BonesimError, match="exists"):
        SessionWriter(p, HEADER)


def test_a_second_writer_is_refused(tmp_path):
    p = tmp_path / "w.h5"
    w = SessionWriter(p, HEADER, compact=False)
    with pytest.raises(BonesimError, match="another process is writing"):
        GuardedFile(p, overwrite=True)
    w.close()


def _fill_until_failure(w, rows=2000, rounds=200):
    t0 = 0
    for _ in range(rounds):
        t = (t0 + np.arange(rows)) * 1e-3
        w.append("samples", {"t_s": t, "pos_mm": np.ones((rows, 3)),
                             "axis": np.tile([1.0, 0, 0], (rows, 1))})
        w.append("tissue", {"t_s": t[::10], "kind": np.zeros(len(t[::10]), np.uint8)})
        w.flush()
        t0 += rows
        if w.failed:
            return t0
    raise AssertionError("the limit was never reached")


def test_writer_on_a_full_disk_stops_and_keeps_what_it_says(tmp_path, no_reserve):
    p = tmp_path / "full.h5"
    with file_size_limit(3 * MB):
        w = SessionWriter(p, HEADER)
        sent = _fill_until_failure(w)
        w.close()                                  # nothing raises, no crash
    assert "largest size allowed" in w.failed
    kept = w.kept
    assert 0 < kept["samples"] < sent and kept["removals"] > 0
    line = kept_line(p, w.failed, kept)
    assert "\n" not in line and f"{kept['samples']:,} samples" in line
    s = read_session(p)                            # the file holds at least that
    assert not s.complete and s.damage is not None
    t = s.samples["t_s"]
    assert kept["samples"] <= len(t) <= kept["samples"] + 2000
    np.testing.assert_array_equal(t, np.arange(len(t)) * 1e-3)     # no zero rows
    assert np.all(s.samples["axis"][:, 0] == 1.0)
    assert not compaction_temp(p).exists()


def test_writer_stops_cleanly_when_the_space_runs_low(tmp_path, monkeypatch):
    p = tmp_path / "low.h5"
    w = SessionWriter(p, HEADER)
    w.append("samples", {"t_s": np.arange(100) * 1e-3})
    w.flush()
    monkeypatch.setattr(disk_guard, "headroom_bytes", lambda path: 1 * MB)
    w._next_check = 0.0
    w.append("samples", {"t_s": (100 + np.arange(100)) * 1e-3})
    w.flush()
    assert "nearly full" in w.failed and w.f is None          # closed, complete
    s = read_session(p)
    assert s.complete and s.damage is None and len(s.samples["t_s"]) == 200
    assert "nearly full" in s.stopped
    assert "stopped early" in coverage(s)["short"]


def test_compaction_out_of_room_keeps_the_raw_file_and_no_temporary(tmp_path):
    p = tmp_path / "c.h5"
    write_synthetic(p, compact=False)
    raw = p.read_bytes()
    with file_size_limit(len(raw) // 20):          # the copy cannot fit
        with pytest.raises(BonesimError) as err:
            compact_session(p)
    msg = str(err.value)
    assert "\n" not in msg and "compacting stopped" in msg and "kept as it was" in msg
    assert p.read_bytes() == raw and not compaction_temp(p).exists()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["c.h5"]


def test_compaction_removes_a_stale_temporary_first(tmp_path):
    p = tmp_path / "s.h5"
    write_synthetic(p, compact=False)
    compaction_temp(p).write_bytes(b"junk left by a killed compaction")
    compact_session(p)
    assert not compaction_temp(p).exists() and read_session(p).damage is None


def test_space_is_checked_before_a_run(tmp_path):
    p = tmp_path / "r.h5"
    with file_size_limit(20 * MB):
        with pytest.raises(BonesimError, match=r"not enough space to record the 600.0 s "
                                               r"run: about \d+\.\d MB needed"):
            check_space(p, 600.0, 1000.0)
        assert check_space(p, 2.0, 1000.0) is None
        warn = check_space(p, None, 1000.0)          # an interactive run: a warning
        assert "room for only about" in warn and "min of recording" in warn
    with file_size_limit(1 * MB):
        with pytest.raises(BonesimError, match="only 1.0 MB can be written"):
            check_space(p, 2.0, 1000.0)
    assert not p.exists()


def test_simulate_on_a_disk_that_fills_exits_non_zero_with_the_kept_span(
        tmp_path, capsys, monkeypatch, no_reserve):
    """``bonesim simulate --record`` on a disk that fills during the run (the
    check before passed): one line, exit status 3, record_ok false and the kept
    span in the JSON, and the file holds that span, no zero rows."""
    from bonesim.io.case import load_case
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.io.trajectory import write_trajectory

    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    script = tmp_path / "s.csv"
    write_trajectory(script, t.at_times(t.t_s[start:start + 1400]))
    monkeypatch.setattr(disk_guard, "check_space", lambda *a, **k: None)
    out = tmp_path / "sim.h5"
    # (room for the header, the recorded case and the first chunks of each stream)
    with file_size_limit(int(1.8 * MB)):
        rc = main(["simulate", "--trajectory", str(script), "--record", str(out), "--json"])
    cap = capsys.readouterr()
    assert rc == EXIT_RECORDING_LOST == 3
    res = json.loads(cap.out)
    assert res["record_ok"] is False and res["voxels_removed"] > 0
    kept = res["record_kept"]
    assert 0 < kept["samples"] < res["steps"], (res, cap.err)
    err = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("bonesim: recording stopped at")
    assert "largest size allowed" in err[0] and "Traceback" not in cap.err
    s = read_session(out)
    t = s.samples["t_s"]
    assert len(t) >= kept["samples"] and t[-1] - kept["t_s"] <= 2.1   # one half ring
    assert np.all(np.diff(t) > 0)
    assert np.all(np.linalg.norm(s.samples["axis"], axis=1) > 0.5)      # no zero rows
    assert len(s.removals["t_s"]) >= kept["removals"]


def test_repair_onto_a_full_disk_says_so_and_leaves_nothing(tmp_path):
    from bonesim.session.reader import repair_session

    src = tmp_path / "src.h5"
    write_synthetic(src, compact=False)
    out = tmp_path / "fixed.h5"
    with file_size_limit(300_000):
        with pytest.raises(BonesimError, match="repaired copy could not be written: the "
                                               "file reached the largest size allowed"):
            repair_session(src, out)
    assert not out.exists() and not compaction_temp(out).exists()


_SLOW_COMPACTION = """
import sys, time, h5py
from bonesim.session import writer
writer.COMPACT_CHUNK_ROWS = 256
orig = h5py.Dataset.__setitem__
def slow(self, key, value):
    time.sleep(0.02)
    return orig(self, key, value)
h5py.Dataset.__setitem__ = slow
writer.compact_session(sys.argv[1])
"""


def test_a_killed_compaction_leaves_the_session_whole_and_its_leftover_named(tmp_path):
    """SIGKILL while compacting: the session is untouched and reads whole; the
    temporary is recognised as a leftover (never read as a session) and the
    next compaction removes it."""
    import subprocess
    import sys
    import time

    from bonesim.session.reader import list_sessions

    p = tmp_path / "k.h5"
    data = write_synthetic(p, compact=False)
    raw = p.read_bytes()
    tmp = compaction_temp(p)
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_COMPACTION, str(p)])
    try:
        end = time.monotonic() + 120
        while not (tmp.exists() and tmp.stat().st_size > 20_000):
            assert proc.poll() is None and time.monotonic() < end
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait(30)
    assert p.read_bytes() == raw and tmp.exists()
    s = read_session(p)
    assert s.complete and s.damage is None and len(s.samples["t_s"]) == len(data["samples"]["t_s"])
    with pytest.raises(BonesimError, match="leftover of an interrupted compaction"):
        read_session(tmp)
    rows = {r["file"]: r for r in list_sessions(tmp_path)}
    assert "leftover" in rows[str(tmp)]["error"] and rows[str(p)]["complete"]
    compact_session(p)
    assert not tmp.exists() and read_session(p).damage is None
