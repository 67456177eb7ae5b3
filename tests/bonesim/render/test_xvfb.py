"""The interactive window's timer loop on a virtual X server (Xvfb).

Skipped only when Xvfb is not installed (Debian: ``apt-get install xvfb``).
The window runs in a child process so that the X window class is chosen
there (this process renders offscreen)."""
from __future__ import annotations

import json
import os
import random
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
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


def test_timer_loop_under_xvfb(xdisplay, tmp_path):
    out = tmp_path / "xloop.json"
    env = dict(os.environ, DISPLAY=xdisplay, PYTHONPATH=str(ROOT))
    env.pop("BONESIM_GL", None)
    res = subprocess.run([sys.executable, "-m", "tests.bonesim.render.xloop", str(out), "40"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr[-3000:]
    rec = json.loads(out.read_text())
    assert rec["window"] == "vtkXOpenGLRenderWindow"
    assert rec["mapped"] and not rec["offscreen"]
    assert rec["summary"]["frames"] == 40 and rec["summary"]["frame_hz"] > 1.0
    tris = rec["triangles"]
    assert len(tris) == 41 and len(set(tris)) > 3          # the mesh changed while drawn
    # the HUD shows both rates, with numbers
    hud = rec["final_hud"]
    assert re.search(r"rate: haptic 1000 Hz  frame \d+ Hz", hud), hud
    assert rec["frame_hz"] > 1.0
    assert rec["keys"] == ["drill_toggle"] and rec["mouse"] >= 1
