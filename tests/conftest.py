"""Fixtures shared by the whole suite."""
from __future__ import annotations

import random
import shutil
import subprocess
import time
from pathlib import Path

import pytest


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
