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
from bonesim.runtime.record import Recorder, make_header
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
