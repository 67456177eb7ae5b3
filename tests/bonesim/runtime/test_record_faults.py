"""A recording either completes or says it did not (issue 24): ``bonesim run``
watches its writer process. Killed mid-run, or on a disk that fills (a real
``RLIMIT_FSIZE`` in the writer process, through its test hook), the run goes
on, says once in the window and on stderr what the file keeps and up to
when, exits with status 3, and its JSON carries ``record_ok`` false and the
kept span, which is what the file holds."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bonesim.errors import EXIT_RECORDING_LOST
from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory
from bonesim.io.trajectory import write_trajectory
from bonesim.session.reader import read_session

#: Offscreen frames of a run (the writer is killed, or its disk fills, within
#: the first second of the haptic loop; the scene's start and these frames
#: take longer).
FRAMES = 90


@pytest.fixture(scope="module")
def script(tmp_path_factory):
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    path = tmp_path_factory.mktemp("script") / "s.csv"
    write_trajectory(path, t.at_times(t.t_s[start:start + 2000]))
    return path


def _run(script, out: Path, env=None) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "bonesim", "run", "--offscreen", "--script", str(script),
           "--frames", str(FRAMES), "--record", str(out), "--no-sound", "--json",
           "--screenshot", str(out.with_suffix(".png"))]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **(env or {})}, start_new_session=True)


def _holder(path: Path) -> int | None:
    """The process that holds ``path`` open (the writer)."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            for fd in (d / "fd").iterdir():
                if os.readlink(fd) == str(path):
                    return int(d.name)
        except OSError:
            continue
    return None


def _finish(proc, timeout=600):
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    return proc.returncode, out, err


def _check_report(rc, out, err, path, why):
    assert rc == EXIT_RECORDING_LOST, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("bonesim: recording stopped")]
    assert len(lines) == 1 and why in lines[0], err[-3000:]
    assert "Traceback" not in err
    res = json.loads(out)
    assert res["record_ok"] is False and res["record"] == str(path)
    assert res["record_error"] == lines[0][len("bonesim: "):]
    assert any(n == res["record_error"] for n in res["notices"])     # the window's line
    kept = res["record_kept"]
    assert f"{kept['samples']:,} samples" in lines[0]
    assert res["voxels_removed"] > 0                                  # the run went on
    return res, kept


@pytest.mark.slow
def test_a_killed_writer_stops_the_recording_with_one_line_and_status_3(script, tmp_path):
    path = tmp_path / "killed.h5"
    proc = _run(script, path)
    try:
        end = time.monotonic() + 400
        while time.monotonic() < end:
            if path.exists():
                try:
                    if len(read_session(path).samples["t_s"]) > 300:
                        break
                except Exception:
                    pass
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            time.sleep(0.1)
        writer = _holder(path)
        assert writer is not None and writer != proc.pid
        os.kill(writer, signal.SIGKILL)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    rc, out, err = _finish(proc)
    res, kept = _check_report(rc, out, err, path, "the recorder process died (killed by "
                                                   "signal 9)")
    s = read_session(path)                      # the file holds the kept span (or one
    assert not s.complete                       # flush more: the status lags the flush)
    t = s.samples["t_s"]
    assert kept["samples"] <= len(t) and t[-1] - kept["t_s"] <= 0.2
    assert len(s.removals["t_s"]) >= kept["removals"]


@pytest.mark.slow
def test_a_full_disk_in_the_writer_stops_the_recording_with_the_kept_span(script,
                                                                         tmp_path):
    path = tmp_path / "full.h5"
    proc = _run(script, path, env={"BONESIM_TEST_WRITER_FSIZE": str(1 << 20)})
    rc, out, err = _finish(proc)
    res, kept = _check_report(rc, out, err, path, "largest size allowed")
    assert path.stat().st_size <= 1 << 20
    s = read_session(path)
    # at least the kept span (a failed flush may have landed some columns whole)
    t = s.samples["t_s"]
    assert s.damage is not None and len(t) >= kept["samples"] > 0
    assert t[-1] - kept["t_s"] <= 0.2 and np.all(np.diff(t) > 0)
    assert np.all(np.linalg.norm(s.samples["axis"], axis=1) > 0.5)    # no zero rows
    assert len(s.removals["t_s"]) >= kept["removals"]
