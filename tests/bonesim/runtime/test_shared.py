"""Shared memory and child processes: a child ends with its parent."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

_CHILD = """
import json, sys, time
sys.path.insert(0, sys.argv[2])
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.io.loading import load_model
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
m = load_model("phantom", "cutting-5mm")
loop = HapticLoop(m, device=("null",))
rec = Recorder(loop, sys.argv[1], make_header(m)).start()
loop.start()
print(json.dumps({"loop": loop.pid, "writer": rec.pid}), flush=True)
while True:
    time.sleep(1)
"""


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for its new parent to reap it counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_children_end_when_the_parent_is_killed(tmp_path):
    from bonesim.session.reader import read_session

    path = tmp_path / "orphan.h5"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path), str(ROOT)],
                            stdout=subprocess.PIPE, text=True)
    try:
        pids = json.loads(proc.stdout.readline())
        time.sleep(0.5)
        assert all(_alive(p) for p in pids.values())
    finally:
        os.kill(proc.pid, signal.SIGKILL)            # the parent only
        proc.wait(10)
    end = time.monotonic() + 10.0
    while any(_alive(p) for p in pids.values()) and time.monotonic() < end:
        time.sleep(0.05)
    assert not any(_alive(p) for p in pids.values()), pids   # no spinning orphan loop
    # the writer, told by SIGTERM, drained the rings and closed its file
    s = read_session(path)
    assert s.complete and len(s.samples["t_s"]) > 100


# ---------------------------------------------------------------- leftovers
# Issue 24: kill -9 of a run's process group left ~107 MB of /dev/shm/psm_*
# each time (the resource tracker dies with it). Blocks now carry the prefix
# and their owner's pid; the survivor frees them, the next start reclaims them.

_OWNER = """
import multiprocessing.resource_tracker as rt, sys, time
sys.path.insert(0, sys.argv[1])
from tests.bonesim.runtime.test_child import Counter
c = Counter().start(60.0)
rt.ensure_running()
print(c.handle[0], c.pid, rt._resource_tracker._pid, flush=True)
while True:
    time.sleep(1)
"""

_LINUX_SHM = pytest.mark.skipif(not Path("/dev/shm").is_dir(), reason="needs /dev/shm")


def _dead_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@_LINUX_SHM
def test_blocks_are_named_with_the_prefix_and_their_owner_pid():
    from bonesim.runtime.shared import PREFIX, SHM_DIR, SharedArrays, owner_pid

    sh = SharedArrays.create([("a", (10,), "f8")])
    try:
        name = sh.handle[0]
        assert name.startswith(PREFIX) and owner_pid(name) == os.getpid()
        assert (SHM_DIR / name).exists()
    finally:
        sh.close()
    assert not (SHM_DIR / name).exists()
    assert owner_pid("psm_1234") is None and owner_pid("bonesim_12_ab") == 12


@_LINUX_SHM
def test_a_block_of_a_dead_run_is_reclaimed_at_the_next_start(monkeypatch, capsys):
    from bonesim.runtime import shared
    from bonesim.runtime.shared import SHM_DIR, SharedArrays, block_name

    dead = block_name(_dead_pid())
    (SHM_DIR / dead).write_bytes(b"\0" * 4096)          # what a SIGKILLed run leaves
    alive = block_name(os.getppid())                    # a live owner's: kept
    (SHM_DIR / alive).write_bytes(b"\0" * 4096)
    try:
        monkeypatch.setattr(shared, "_reclaimed", False)  # this process's first block
        sh = SharedArrays.create([("a", (4,), "f8")])
        sh.close()
        assert not (SHM_DIR / dead).exists()
        assert (SHM_DIR / alive).exists()
        err = capsys.readouterr().err
        assert "reclaimed" in err and dead.split("_")[1] in err and err.count("\n") == 1
        assert shared.reclaim_leftovers(quiet=True) == []   # nothing more to free
    finally:
        for n in (dead, alive):
            (SHM_DIR / n).unlink(missing_ok=True)


@pytest.mark.slow
@_LINUX_SHM
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_child_frees_the_block_when_its_parent_and_tracker_are_killed():
    """The parent and its resource tracker get SIGKILL (nobody left to unlink
    on their side); the child, told by SIGTERM, is the survivor and frees it."""
    from bonesim.runtime.shared import SHM_DIR

    proc = subprocess.Popen([sys.executable, "-c", _OWNER, str(ROOT)],
                            stdout=subprocess.PIPE, text=True)
    try:
        name, child, tracker = proc.stdout.readline().split()
        assert (SHM_DIR / name).exists() and _alive(int(child))
        os.kill(int(tracker), signal.SIGKILL)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    end = time.monotonic() + 20.0
    while (SHM_DIR / name).exists() and time.monotonic() < end:
        time.sleep(0.05)
    exists = (SHM_DIR / name).exists()
    (SHM_DIR / name).unlink(missing_ok=True)
    assert not exists, "the surviving child left the block behind"
    while _alive(int(child)) and time.monotonic() < end:
        time.sleep(0.05)
    assert not _alive(int(child))


@_LINUX_SHM
def test_the_parent_frees_the_block_when_its_child_is_killed():
    from bonesim.runtime.shared import SHM_DIR
    from tests.bonesim.runtime.test_child import PATIENT_S, Counter

    c = Counter().start(PATIENT_S)
    name = c.handle[0]
    os.kill(c.pid, signal.SIGKILL)
    c.close()
    assert not (SHM_DIR / name).exists()


@pytest.mark.slow
@_LINUX_SHM
def test_kill_9_of_the_process_group_leaves_a_block_the_next_start_reclaims():
    """Issue 24 as reported: kill -9 of the run's whole process group (owner,
    child and resource tracker) leaves the block; the next start frees it."""
    from bonesim.runtime.shared import SHM_DIR

    proc = subprocess.Popen([sys.executable, "-c", _OWNER, str(ROOT)],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        name, child, _ = proc.stdout.readline().split()
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    end = time.monotonic() + 20.0
    while _alive(int(child)) and time.monotonic() < end:
        time.sleep(0.05)
    try:
        assert (SHM_DIR / name).exists()                 # nobody was left to free it
        nxt = subprocess.run(
            [sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]);"
             "from bonesim.runtime.shared import SharedArrays;"
             "SharedArrays.create([('a', (4,), 'f8')]).close()", str(ROOT)],
            capture_output=True, text=True, timeout=120)
        assert nxt.returncode == 0, nxt.stderr
        assert not (SHM_DIR / name).exists()
        assert "reclaimed" in nxt.stderr and "left by dead run(s)" in nxt.stderr
    finally:
        (SHM_DIR / name).unlink(missing_ok=True)


def test_a_seqlocked_read_is_one_writes_snapshot_or_none():
    """The haptic loop's per-step status is read whole (read_seqlocked): a
    copy never mixes two steps; while the writer is mid-step (odd seq) no
    copy is returned."""
    import threading

    import numpy as np

    from bonesim.runtime.shared import read_seqlocked

    st = {"seq": np.zeros((), np.int64), "t_s": np.zeros((), np.float64),
          "pos_mm": np.zeros(3)}
    stop = threading.Event()

    def writer():
        n = 0
        while not stop.is_set():
            n += 1
            st["seq"][...] += 1
            st["t_s"][...] = n
            for k in range(3):                  # field by field, as the loop does
                st["pos_mm"][k] = n
            st["seq"][...] += 1

    th = threading.Thread(target=writer)
    th.start()
    try:
        got = [read_seqlocked(st, ("t_s", "pos_mm")) for _ in range(20000)]
    finally:
        stop.set()
        th.join()
    whole = [g for g in got if g is not None]
    assert len(whole) > 1000
    assert all((g["pos_mm"] == g["t_s"]).all() for g in whole)
    st["seq"][...] = 7                          # a writer that stopped mid-step
    assert read_seqlocked(st, ("t_s",), tries=10) is None
