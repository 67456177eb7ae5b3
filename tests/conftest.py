"""Fixtures shared by the whole suite."""
from __future__ import annotations

import random
import shutil
import subprocess
import time
from pathlib import Path

import pytest

#: Seconds each test file took on a quiet 2-core machine (``pytest -n 2
#: --file-seconds tests/file_seconds.json`` writes it anew). The files are
#: handed to the workers longest first, so that a long file does not start
#: last and leave the other worker idle (longest-processing-time-first).
FILE_SECONDS = Path(__file__).with_name("file_seconds.json")

#: Seconds per test assumed for a file the table does not list.
NEW_TEST_S = 0.2


def pytest_addoption(parser):
    parser.addoption("--file-seconds", metavar="PATH", default=None,
                     help="write the seconds each test file took (setup, call and "
                          "teardown of its tests) to PATH as JSON")


#: The per-file seconds of this run (``--file-seconds``), summed from the
#: reports (in a distributed run the controller receives every worker's).
_SECONDS: dict = {}


def pytest_configure(config):
    # keep the order set below: xdist's --dist loadfile otherwise hands out
    # the files with the most tests first, which puts long files of few
    # tests (end-to-end runs) last
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    import json

    known = json.loads(FILE_SECONDS.read_text()) if FILE_SECONDS.exists() else {}
    first, count = {}, {}
    for k, it in enumerate(items):
        f = it.nodeid.split("::", 1)[0]
        first.setdefault(f, k)
        count[f] = count.get(f, 0) + 1
    weight = {f: known.get(f, NEW_TEST_S * n) for f, n in count.items()}

    def key(it):
        f = it.nodeid.split("::", 1)[0]
        return -weight[f], first[f]

    items.sort(key=key)                    # stable: a file's tests keep their order


def pytest_runtest_logreport(report):
    f = report.nodeid.split("::", 1)[0]
    _SECONDS[f] = _SECONDS.get(f, 0.0) + report.duration


def pytest_sessionfinish(session):
    import json

    out = session.config.getoption("--file-seconds")
    if out and not hasattr(session.config, "workerinput"):
        secs = {f: round(s, 1) for f, s in sorted(_SECONDS.items())}
        Path(out).write_text(json.dumps(secs, indent=1) + "\n")


@pytest.fixture(scope="session", autouse=True)
def _sessions_folder(tmp_path_factory):
    """Interactive runs record by default and cohorts cache their runs' scores:
    keep their files out of $HOME."""
    import os

    os.environ["BONESIM_SESSIONS"] = str(tmp_path_factory.mktemp("sessions"))
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))
    yield


@pytest.fixture(scope="session")
def xdisplay():
    """A private Xvfb server on a random display number; yields ``":N"``."""
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb); "
                    "the interactive-window test needs an X server")
    rng = random.Random()
    for _ in range(8):
        n = rng.randint(200, 30000)
        if Path(f"/tmp/.X{n}-lock").exists() or Path(f"/tmp/.X11-unix/X{n}").exists():
            continue
        proc = subprocess.Popen([exe, f":{n}", "-screen", "0", "640x480x24", "-nolisten",
                                 "tcp", "-noreset"], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        sock = Path(f"/tmp/.X11-unix/X{n}")
        t_end = time.monotonic() + 15.0
        while time.monotonic() < t_end and proc.poll() is None and not sock.exists():
            time.sleep(0.05)
        if proc.poll() is None and sock.exists():
            try:
                yield f":{n}"
            finally:
                proc.terminate()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            return
        proc.kill()
        proc.wait()
    pytest.fail("could not start Xvfb on any of 8 random display numbers")
