"""``bonesim warmup`` compiles every kernel signature a real run needs.

A kernel that meets new argument types (a read-only array where the warm-up
passed a writable one) compiles again at first use: on a cold cache that
stalled the haptic loop's first step for 1.8 s and the window's start for
2 s. So, in a fresh process (whose dispatchers know only what it compiled or
loaded), the warm-up runs, then the phantom goes through what the loop, the
surface consumer, the window's buffers and the nerve monitor do, and no
kernel may gain a signature.
"""
from __future__ import annotations

import importlib
import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

_CHILD = r"""
import importlib, json, pickle, pkgutil
import numpy as np
from numba.core.registry import CPUDispatcher
import bonesim, bonesim.render
W = importlib.import_module("bonesim.cli.warmup")

def signatures():
    out = {}
    for pkg in (bonesim, bonesim.render):
        for info in pkgutil.iter_modules(pkg.__path__):
            name = pkg.__name__ + "." + info.name
            if info.ispkg or name in ("bonesim.render.scene", "bonesim.render.window",
                                      "bonesim.render.gl", "bonesim.render.bench",
                                      "bonesim.render.hud", "bonesim.render.trace",
                                      "bonesim.render.playback"):
                continue                      # VTK modules: no kernels
            mod = importlib.import_module(name)
            for k, v in vars(mod).items():
                if isinstance(v, CPUDispatcher) and v.__module__ == name:
                    out[name + "." + k] = sorted(map(str, v.signatures))
    return out

for name, fn in W._parts():
    if name != "haptic loop":             # its own process: checked below in this one
        fn()
before = signatures()

from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory
from bonesim.io.loading import load_model
from bonesim.engine.model import make_state, step
from bonesim.runtime.monitor import NerveMonitor
from bonesim.render.meshbuf import SurfaceBuffers
from bonesim.engine.replica import TissueReplica

model = load_model("phantom", "cutting-5mm")
sent = pickle.loads(pickle.dumps(model))        # as the loop's process gets it
state = make_state(sent)
consumer = TissueReplica(model, state, surface=True)
traj = demo_trajectory(load_case("phantom"), "cutting-5mm").resample(1000.0)
start = int(np.flatnonzero(traj.drill)[0])
buf = SurfaceBuffers()
for q, s in enumerate(traj.samples()):
    if q < start:
        continue
    step(sent, state, s)
    if q % 50 == 0:
        ch = consumer.drain()
        buf.sync(consumer.surface, ch.removed, ch.touched)
    if q > start + 4000:
        break
assert state.n_removed > 0
NerveMonitor(model)
after = signatures()
new = {k: sorted(set(v) - set(before.get(k, []))) for k, v in after.items()}
print(json.dumps({k: v for k, v in new.items() if v}))
"""


def test_warmup_covers_the_types_of_a_real_run():
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    new = json.loads(out.stdout.strip().splitlines()[-1])
    assert new == {}, f"kernels compiled after the warm-up: {new}"


def test_warmup_says_what_it_does(monkeypatch, capsys):
    """The one-time compile is announced, and each part is named before it
    starts (the first part alone takes tens of seconds cold)."""
    from bonesim.cli.main import main

    W = importlib.import_module("bonesim.cli.warmup")
    ran = []
    monkeypatch.setattr(W, "_parts", lambda: [("first", lambda: ran.append(1)),
                                               ("second", lambda: ran.append(2))])
    assert main(["warmup"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert ran == [1, 2] and "once" in lines[0] and "cached" in lines[0]
    assert lines[1].split()[:3] == ["[", "1/2]", "first"] and lines[1].endswith(" s")
    assert lines[2].split()[:2] == ["[", "2/2]"] and lines[-1].startswith("compiled")
    assert main(["warmup", "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)["seconds"]) == {"first", "second"}


def test_two_processes_compile_every_part_once(tmp_path):
    """With two processes the child compiles the parts of SECOND and the
    parent the rest: every part is reported once, and a child that fails is
    one line, not a silent gap."""
    import os

    from bonesim.cli.warmup import SECOND, _parts

    root = str(__import__("pathlib").Path(__file__).resolve().parents[3])
    env = dict(os.environ, PYTHONPATH=root)
    res = subprocess.run([sys.executable, "-m", "bonesim", "warmup", "--jobs", "2"],
                         capture_output=True, text=True, timeout=900, env=env, cwd=root)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = res.stdout.splitlines()
    assert "2 processes side by side" in lines[0] and lines[-1].startswith("compiled")
    names = [n for n, _ in _parts()]
    shown = [ln.split("]", 1)[1].rsplit(None, 2)[0].strip() for ln in lines[1:-1]]
    assert sorted(shown) == sorted(names) and set(SECOND) <= set(names)
    assert [ln.split("]")[0].split("[")[1].strip() for ln in lines[1:-1]] == [
        f"{k}/{len(names)}" for k in range(1, len(names) + 1)]


def test_a_failed_second_process_is_one_line(monkeypatch, capsys):
    from bonesim.cli.main import main

    W = importlib.import_module("bonesim.cli.warmup")
    monkeypatch.setattr(W, "_parts", lambda: [("first", lambda: None),
                                               ("surface", lambda: None)])
    monkeypatch.setattr(W.sys, "executable", "/bin/false")
    assert main(["warmup", "--jobs", "2"]) == 2
    err = capsys.readouterr().err
    assert "the warm-up's second process failed (exit 1)" in err and "Traceback" not in err
