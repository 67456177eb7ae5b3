"""Schema 4 session files carry their model: they play back, replay bit for
bit and score with every case and burr file gone and the materials changed
(:mod:`bonesim.io.embedded`, :meth:`bonesim.session.reader.Session.burr_models`,
``sessions info --against-current``)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from bonesim.io.case import load_case
from bonesim.io.embedded import MODEL_GROUP
from bonesim.io.loading import load_model
from bonesim.io.toolpath import demo_trajectory
from bonesim.runtime.simulate import run_trajectory
from bonesim.session.drift import against_current
from bonesim.session.header import make_header, model_sha256
from bonesim.session.reader import read_session
from bonesim.session.replay import verify

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def recorded(model, tmp_path_factory):
    """3 s of the planned demo from its first drilling sample, recorded."""
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    traj = t.at_times(t.t_s[start:start + 300])
    path = tmp_path_factory.mktemp("rec") / "run.h5"
    run_trajectory(model, traj, surface=False, record=path)
    return path


def test_the_file_holds_the_model_and_rebuilds_it(recorded, model):
    s = read_session(recorded)
    assert s.schema == 4 and s.carries_model
    rec = s.header["model"]
    assert [b["name"] for b in rec["burrs"]] == ["cutting-5mm"]
    assert set(rec["materials"]) == {st.kind for st in model.structures}
    with h5py.File(recorded, "r") as f:
        labels = f[MODEL_GROUP]["labels"][()]
        assert f[MODEL_GROUP]["labels"].compression == "gzip"
    vol = load_case("phantom").load_volume()
    assert np.array_equal(labels, vol.labels)
    (m,) = s.burr_models()
    assert m.case.volume.format == "session" and m.case.manifest == recorded.resolve()
    assert model_sha256(m) == model_sha256(model)
    # what the physics and the pictures read besides the grid
    assert [st.display_color for st in m.case.structures] == \
        [st.display_color for st in model.case.structures]
    assert m.case.camera == model.case.camera
    assert np.array_equal(m.colors, model.colors)
    # the scripted run stored the eye its removals were judged from
    assert len(s.camera["t_s"]) == 1
    assert np.allclose(s.camera["eye_mm"][0], model.case.camera.eye_mm)


def test_a_damaged_model_falls_back_to_the_case_files_else_one_clear_error(
        recorded, model, tmp_path, monkeypatch):
    from bonesim.errors import BonesimError
    from bonesim.session.reader import Session

    bad = tmp_path / "bad.h5"
    bad.write_bytes(recorded.read_bytes())
    with h5py.File(bad, "r+") as f:
        del f[MODEL_GROUP]["labels"]
    s = read_session(bad)
    (m,) = s.burr_models()                 # today's phantom still builds it
    assert "/model/labels is missing" in s.model_source
    assert model_sha256(m) == model_sha256(model) and m.case.volume.format == "phantom"

    def gone(self, check):
        raise BonesimError("no bundled case named 'phantom'")

    monkeypatch.setattr(Session, "_models_from_files", gone)
    with pytest.raises(BonesimError, match=r"/model/labels is missing"):
        read_session(bad).burr_models()


def test_a_file_without_the_model_still_rebuilds_from_the_case_files(model, tmp_path):
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    header = make_header(model)
    del header["model"]                    # as schemas 1 to 3 wrote them
    path = tmp_path / "old-style.h5"
    run_trajectory(model, t.at_times(t.t_s[start:start + 50]), surface=False,
                   record=path, header=header)
    s = read_session(path)
    assert not s.carries_model
    with h5py.File(path, "r") as f:
        assert MODEL_GROUP not in f
    assert model_sha256(s.load_model()) == model_sha256(model)
    assert verify(s)["ok"]


def test_against_current_lists_what_changed(recorded, monkeypatch, tmp_path):
    s = read_session(recorded)
    same = against_current(s)
    assert same["differs"] == 0 and same["self_contained"]
    assert [i["what"] for i in same["items"]] == ["case phantom", "burr 0 cutting-5mm",
                                                  "materials", "model"]
    # today's bone cuts twice as fast
    from bonesim.engine import materials as mat_mod

    text = mat_mod.default_materials_path().read_text()
    changed = tmp_path / "materials.toml"
    changed.write_text(text.replace("[bone]", "[bone]\n# faster").replace(
        "removal = 1.0", "removal = 2.0", 1))
    assert changed.read_text() != text
    monkeypatch.setattr(mat_mod, "default_materials_path", lambda: changed)
    d = {i["what"]: i for i in against_current(s)["items"]}
    assert d["materials"]["status"] == "differs" and "bone" in d["materials"]["detail"]
    assert d["case phantom"]["status"] == "same"


_SCRIPT = textwrap.dedent("""
    import contextlib, io, json, sys
    from bonesim.engine import materials
    from pathlib import Path
    materials.default_materials_path = lambda: Path(sys.argv[2])
    from bonesim.cli.main import main
    out = {}
    for name, argv in [
            ("info", ["sessions", "info", sys.argv[1], "--against-current", "--json"]),
            ("replay", ["replay", sys.argv[1], "--verify", "--json"]),
            ("metrics", ["metrics", "run", sys.argv[1], "--json"]),
            ("assess", ["assess", sys.argv[1], "--json"]),
            ("playback", ["playback", sys.argv[1], "--offscreen", "--frames", "2",
                          "--screenshot", "shot.png", "--no-progress"])]:
        buf, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
            code = main(argv)
        out[name] = {"code": code, "out": buf.getvalue(), "err": err.getvalue()}
    print(json.dumps(out))
""")


def test_plays_back_replays_and_scores_with_no_case_or_burr_files(tmp_path):
    """A run recorded on a copy of the phantom's case folder, which is then
    deleted; a fresh process in which the bundled cases and burrs are empty
    packages (shadowing the shipped ones) and the bone's material has changed."""
    import shutil

    from bonesim.io.case import cases_dir

    folder = tmp_path / "case"
    shutil.copytree(cases_dir() / "phantom", folder)
    model = load_model(folder / "case.toml", "cutting-5mm")
    t = demo_trajectory(model.case, "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    recorded = tmp_path / "run.h5"
    run_trajectory(model, t.at_times(t.t_s[start:start + 300]), surface=False,
                   record=recorded)
    here = json.loads(subprocess.run(
        [sys.executable, "-m", "bonesim", "metrics", "run", str(recorded), "--json"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path).stdout)
    shutil.rmtree(folder)
    shadow = tmp_path / "shadow"
    for pkg in ("ct_cases", "burrs"):          # the packages, with no file in them
        (shadow / pkg).mkdir(parents=True)
        (shadow / pkg / "__init__.py").write_text(
            "from pathlib import Path\n"
            "CASES_DIR = Path(__file__).resolve().parent\n"
            "def folder():\n    return CASES_DIR\n")
    mats = tmp_path / "materials.toml"
    from bonesim.engine.materials import default_materials_path

    mats.write_text(default_materials_path().read_text().replace(
        "removal = 1.0", "removal = 3.0", 1))
    script = tmp_path / "score.py"
    script.write_text(_SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(shadow), str(ROOT)]))
    done = subprocess.run([sys.executable, str(script), str(recorded), str(mats)],
                          capture_output=True, text=True, env=env, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    for name, r in out.items():
        assert r["code"] == 0, (name, r["err"][-1500:])
        assert "Traceback" not in r["err"]
    info = json.loads(out["info"]["out"])["against_current"]
    st = {i["what"]: i["status"] for i in info["items"]}
    assert st["case phantom"] == "missing" and st["burr 0 cutting-5mm"] == "missing"
    assert info["self_contained"]
    rep = json.loads(out["replay"]["out"])
    assert rep["ok"] is True and rep["samples_checked"] == rep["samples_declared"] > 2000
    # the same scores as while the case and burr files were there
    assert json.loads(out["metrics"]["out"]) == here
    assert json.loads(out["assess"]["out"])["items"]
    assert (tmp_path / "shot.png").stat().st_size > 10_000
