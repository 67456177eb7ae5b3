"""The interactive window's timer loop on a virtual X server (Xvfb).

Skipped only when Xvfb is not installed (Debian: ``apt-get install xvfb``);
the ``xdisplay`` fixture lives in ``tests/conftest.py``.
The window runs in a child process so that the X window class is chosen
there (this process renders offscreen)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[3]




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
