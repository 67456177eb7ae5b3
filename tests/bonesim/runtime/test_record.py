"""Session files: write, read back, replay bit for bit, survive SIGKILL, and
refuse files they cannot trust with a clear error."""
from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from multiprocessing import shared_memory

import h5py
import numpy as np
import pytest

from bonesim.engine import events
from bonesim.io.case import load_case
from bonesim.cli.main import main
from bonesim.io.toolpath import demo_trajectory
from bonesim.errors import BonesimError
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.io.loading import load_model
from bonesim.session.schema import SCHEMA_VERSION
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.session.replay import replay, verify
from bonesim.session.reader import read_session, session_info
from bonesim.runtime.shared import SharedArrays
from bonesim.runtime.simulate import run_trajectory
from tests.bonesim.waiting import wait_drill_off, wait_until


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def traj():
    """The planned demo, from its first drilling sample, 8 s long."""
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    return t.at_times(t.t_s[start:start + 800])


@pytest.fixture(scope="module")
def recorded(model, traj, tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "run.h5"
    header = make_header(model, participant="p07", group="novice", notes="first try")
    summary = run_trajectory(model, traj, surface=False, record=path, header=header)
    return path, summary


def test_round_trip_header_streams_and_verify(recorded, model):
    path, summary = recorded
    s = read_session(path)
    assert s.complete and s.schema == SCHEMA_VERSION
    h = s.header
    assert (h["participant"], h["group"], h["notes"]) == ("p07", "novice", "first try")
    assert h["case"]["name"] == "phantom" and len(h["case"]["sha256"]) == 64
    assert h["burrs"][0]["name"] == "cutting-5mm" and h["voxel_mm"] == model.spacing_mm
    assert [st["name"] for st in h["structures"]] == [st.name for st in model.structures]
    n = summary["steps"]
    assert len(s.samples["t_s"]) == n
    assert np.all(np.diff(s.samples["t_s"]) > 0)
    # every removal the run made, in order, with its structure
    assert len(s.removals["t_s"]) == summary["voxels_removed"] > 100
    assert np.all(s.removals["epoch"] == 0)
    # judged from the case camera: the planned path drills in plain view
    vis = s.removals["visible"]
    assert set(np.unique(vis)) <= {0, 1} and vis.mean() > 0.9
    assert np.all(np.linalg.norm(s.samples["force_n"], axis=1) <= model.max_force_n + 1e-9)
    report = verify(s)
    assert report["ok"], report
    info = session_info(s)
    assert info["voxels_removed"] == summary["voxels_removed"]
    assert info["samples"] == n and info["sample_rate_hz"] == 1000.0
    assert info["removals_visible"] == int(np.sum(vis == 1))
    assert info["removals_visible"] + info["removals_hidden"] == len(vis)
    assert info["removals_visibility_unknown"] == 0
    assert info["visible_fraction"] == round(float(np.mean(vis == 1)), 4)


def test_verify_catches_a_changed_removal(recorded, tmp_path):
    path, _ = recorded
    bad = tmp_path / "bad.h5"
    shutil.copy(path, bad)
    with h5py.File(bad, "r+") as f:
        f["tissue/ijk"][5, 0] += 1
    report = verify(read_session(bad))
    assert not report["ok"] and report["first_mismatch"]["index"] == 5
    assert report["first_mismatch"]["field"] == "ijk"
    assert main(["replay", str(bad), "--verify"]) == 1
    assert main(["replay", str(path), "--verify"]) == 0


def test_replay_reproduces_the_final_tissue(recorded, model, traj):
    path, _ = recorded
    out = replay(read_session(path))
    fresh = load_model("phantom", "cutting-5mm")
    from bonesim.engine.model import Sample, make_state, step

    st = make_state(fresh)
    r = traj.resample(fresh.haptic_rate_hz)
    for q in range(len(r.t_s)):
        step(fresh, st, Sample(r.t_s[q], r.pos_mm[q], r.axis[q], bool(r.drill[q]),
                               float(r.speed_rpm[q]), int(r.direction[q])))
    np.testing.assert_array_equal(out["state"].grid.density, st.grid.density)


# ------------------------------------------------------------ schema checks
def _copy_with(path, tmp_path, edit):
    bad = tmp_path / "edited.h5"
    shutil.copy(path, bad)
    with h5py.File(bad, "r+") as f:
        edit(f)
    return bad


@pytest.mark.parametrize("edit, words", [
    (lambda f: f.attrs.__setitem__("schema", SCHEMA_VERSION + 1), "newer"),
    (lambda f: f.attrs.__setitem__("schema", 0), "invalid session schema"),
    (lambda f: f.attrs.__setitem__("format", "something-else"), "not a bonesim session"),
    (lambda f: f.attrs.__setitem__("header", "{not json"), "not JSON"),
    (lambda f: f.attrs.__setitem__("header", json.dumps({"case": {}})), "header lacks"),
    (lambda f: f.__delitem__("tissue"), "/tissue is missing"),
    (lambda f: f["samples"].__delitem__("force_n"), "/samples/force_n is missing"),
    (lambda f: (f["samples"].__delitem__("t_s"),
                f["samples"].create_dataset("t_s", data=np.zeros(3, np.float32))),
     "/samples/t_s has shape"),
])
def test_broken_or_newer_files_get_a_clear_error(recorded, tmp_path, edit, words):
    bad = _copy_with(recorded[0], tmp_path, edit)
    with pytest.raises(BonesimError) as e:
        read_session(bad)
    assert str(bad) in str(e.value) and words in str(e.value)


def test_not_hdf5_and_missing_files(tmp_path, capsys):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not an hdf5 file at all")
    with pytest.raises(BonesimError, match="junk.h5: not an HDF5 file \\(no HDF5 signature"):
        read_session(junk)
    assert main(["sessions", "info", str(tmp_path / "nope.h5")]) == 2
    assert "no such session file" in capsys.readouterr().err


def _resign(f, text: str) -> None:
    """Set the header to ``text`` with a matching checksum (an edit, not damage)."""
    from bonesim.session.schema import FORMAT
    from bonesim.session.header import header_sha256

    f.attrs["header"] = text
    f.attrs["header_sha256"] = header_sha256(FORMAT, int(f.attrs["schema"]), text)


def test_changed_case_is_refused_on_replay(recorded, tmp_path):
    bad = _copy_with(recorded[0], tmp_path, lambda f: _resign(
        f, f.attrs["header"].replace('"model_sha256": ["', '"model_sha256": ["0')))
    # the file's own model (schema 4) no longer matches its recorded hash
    with pytest.raises(BonesimError, match="own record does not hash to the recorded one"):
        replay(read_session(bad))
    # a file without its model (as schemas 1-3) is rebuilt from the case files
    (tmp_path / "files").mkdir()

    def no_model(f):
        del f["model"]
        _resign(f, f.attrs["header"].replace('"model_sha256": ["', '"model_sha256": ["0'))

    bad = _copy_with(recorded[0], tmp_path / "files", no_model)
    with pytest.raises(BonesimError, match="no longer builds the recorded model"):
        replay(read_session(bad))
    # the same edit without its checksum is damage, not a changed case
    (tmp_path / "unsigned").mkdir()
    bad = _copy_with(recorded[0], tmp_path / "unsigned", lambda f: f.attrs.__setitem__(
        "header", f.attrs["header"].replace('"model_sha256": ["', '"model_sha256": ["0')))
    with pytest.raises(BonesimError, match="header is corrupt"):
        replay(read_session(bad))


def test_existing_file_is_not_overwritten(model, traj, recorded):
    with pytest.raises(BonesimError, match="exists"):
        run_trajectory(model, traj, surface=False, record=recorded[0])
    assert read_session(recorded[0]).complete        # untouched


def test_sessions_info_cli_json(recorded, capsys):
    assert main(["sessions", "info", str(recorded[0]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["participant"] == "p07" and info["complete"] is True
    assert set(info["removed_by_structure"]) <= {"bone", "facial_nerve"}    # code names
    assert main(["sessions", "info", str(recorded[0])]) == 0
    text = capsys.readouterr().out
    line = next(ln for ln in text.splitlines() if ln.startswith("removed_by_structure: "))
    assert "Bone " in line and "_" not in line.split(": ", 1)[1]       # clinical names


# ----------------------------------------------------- live loop recording
@pytest.mark.slow
def test_live_loop_recording_replays_bit_for_bit(model, traj, tmp_path):
    """The recorder drains a 1 kHz loop in another process; the recorded
    samples re-stepped give the very same removals and forces."""
    path = tmp_path / "live.h5"
    loop = HapticLoop(model, device=("scripted", traj), run_s=2.0)
    rec = Recorder(loop, path, make_header(model, input_device="scripted"))
    try:
        rec.start()
        loop.start()
        rec.event("key", "drill_toggle")
        rec.camera((0.0, 0.0, 100.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
        assert loop.wait(30.0)
        stats = rec.close()
        n_samples, n_removed = loop.samples.count, loop.state.n_removed
    finally:
        loop.close()
    s = read_session(path)
    assert s.complete and stats["rows"] > 1500
    assert len(s.samples["t_s"]) == n_samples
    assert len(s.removals["t_s"]) == n_removed > 0
    assert s.events[0][1:] == ("key", "drill_toggle") and len(s.camera["t_s"]) == 1
    report = verify(s)
    assert report["ok"], report


_CHILD = r"""
import json, pickle, sys, time
from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.io.loading import load_model
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
import numpy as np
m = load_model("phantom", "cutting-5mm")
t = demo_trajectory(load_case("phantom"), "cutting-5mm")
s = int(np.flatnonzero(t.drill)[0])
loop = HapticLoop(m, device=("scripted", t.at_times(t.t_s[s:])))
rec = Recorder(loop, sys.argv[1], make_header(m)).start()
loop.start()
# handles hold numpy dtypes (structured status records): pickled, as hex
print(json.dumps({"loop": pickle.dumps(loop.handle).hex(),
                  "rec": pickle.dumps(rec.handle).hex(), "writer": rec.pid}), flush=True)
while True:
    time.sleep(1)
"""


def _rows(path) -> int:
    """Samples a live session file holds so far (0 before it can be read)."""
    try:
        return len(read_session(path).samples["t_s"])
    except (BonesimError, OSError):
        return 0


@pytest.mark.slow
def test_sigkill_leaves_a_readable_file_complete_to_the_last_flush(tmp_path):
    path = tmp_path / "killed.h5"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path)],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    handles = None
    try:
        handles = {k: pickle.loads(bytes.fromhex(v)) if k != "writer" else v
                   for k, v in json.loads(proc.stdout.readline()).items()}
        # readable while being written (SWMR), and growing
        assert wait_until(lambda: _rows(path) > 0, 60.0)
        n1 = _rows(path)
        assert wait_until(lambda: _rows(path) > n1, 60.0)
        n2 = _rows(path)
        assert 0 < n1 < n2
        assert wait_until(lambda: _rows(path) > n2, 60.0)     # killed mid-run
    finally:
        os.killpg(proc.pid, signal.SIGKILL)      # the app, the loop and the writer
        proc.wait(10)
    try:
        # the loop's last published time, from its orphaned shared memory
        sh = SharedArrays.attach(handles["loop"])
        t_last = float(sh.arrays["status"]["t_s"])
        n_loop = int(sh.arrays["samples.head"][0])
        sh.close()
    finally:
        for h in (handles["loop"], handles["rec"]):
            try:
                shared_memory.SharedMemory(h[0]).unlink()
            except FileNotFoundError:
                pass
    s = read_session(path)
    assert not s.complete
    t = s.samples["t_s"]
    # what is in the file is exactly what the loop produced, without holes
    assert np.all(np.diff(t) > 0) and len(t) <= n_loop
    assert len(t) >= n2, (len(t), n2, s.damage, s.readable)
    lost_s = t_last - t[-1]
    print(f"SIGKILL: {len(t)} samples in the file, {lost_s * 1e3:.1f} ms lost")
    assert lost_s <= 0.15, f"lost {lost_s * 1e3:.0f} ms of samples"
    assert verify(s)["ok"]


@pytest.mark.slow
def test_live_recording_across_a_reset_and_a_burr_change(model, tmp_path):
    """Mouse drilling, a burr change, a case reset, more drilling: the file
    keeps every removal of both epochs and replays bit for bit."""
    from bonesim.io.burrs import load_burr

    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    target = np.array([23.0, 3.0, -2.0]) + 3.0 * view
    burr2 = load_burr("diamond-3mm")
    path = tmp_path / "reset.h5"
    loop = HapticLoop(model, burrs=[burr2])
    rec = Recorder(loop, path, make_header(model, [burr2], input_device="mouse"))

    try:
        rec.start()
        loop.start()
        loop.set_target(target, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 20)
        loop.set_burr(1)
        n0 = loop.state.n_removed
        assert wait_until(lambda: loop.state.n_removed > n0 + 5)
        epoch = loop.reset()
        assert wait_until(lambda: loop.status["epoch"] == epoch)
        n1 = loop.state.n_removed
        assert wait_until(lambda: loop.state.n_removed > n1 + 20)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        rec.close()
        seen = (int(rec.status["visible"]), int(rec.status["hidden"]))
        ev = loop.state.tissue.read(0)
        n_removed = int((ev["kind"] == events.REMOVED).sum())
    finally:
        loop.close()
    s = read_session(path)
    assert len(s.removals["t_s"]) == n_removed
    # the running counts the window shows: the verdicts since the reset
    vis = s.removals["visible"][s.removals["epoch"] == 1]
    assert seen == (int((vis == 1).sum()), int((vis == 0).sum())) and sum(seen) > 20
    assert set(np.unique(s.removals["epoch"])) == {0, 1}
    assert set(np.unique(s.samples["burr"])) == {0, 1}
    # the loop published the burr change and the reset as tissue events, at
    # the steps that saw them first
    tis = s.tissue
    changes = [(events.KIND_NAMES[k], int(n)) for k, n in zip(tis["kind"], tis["n"])
               if k in (events.BURR, events.RESET)]
    assert changes == [("burr", 1), ("reset", 1)]
    t_burr = float(tis["t_s"][tis["kind"] == events.BURR][0])
    q = np.searchsorted(s.samples["t_s"], t_burr)
    assert s.samples["burr"][q] == 1 and s.samples["burr"][q - 1] == 0
    t_reset = float(tis["t_s"][tis["kind"] == events.RESET][0])
    q = np.searchsorted(s.samples["t_s"], t_reset)
    assert s.samples["epoch"][q] == 1 and s.samples["epoch"][q - 1] == 0
    report = verify(s)
    assert report["ok"], report


def test_sessions_list_shows_good_and_broken_files(recorded, tmp_path, capsys):
    shutil.copy(recorded[0], tmp_path / "a.h5")
    (tmp_path / "b.h5").write_bytes(b"junk")
    assert main(["sessions", "list", str(tmp_path), "--json"]) == 0
    rows = {Path(r["file"]).name: r for r in json.loads(capsys.readouterr().out)["sessions"]}
    assert rows["a.h5"]["participant"] == "p07" and rows["a.h5"]["complete"]
    assert "not an HDF5 file" in rows["b.h5"]["error"]
    assert main(["sessions", "list", str(tmp_path / "none")]) == 2


def _contents(path):
    """Every attribute and column of a session file, as plain values."""
    out = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v)
                        for k, v in f.attrs.items()}

        def visit(name, item):
            if isinstance(item, h5py.Dataset):
                out[name] = item[()]
        f.visititems(visit)
    return out


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if k == "attrs":
            assert {q: str(v) for q, v in a[k].items()} == {q: str(v) for q, v in b[k].items()}
        else:
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k


def test_closing_compacts_the_file_losslessly_and_atomically(model, traj, tmp_path,
                                                            monkeypatch):
    from bonesim.session import writer

    raw = tmp_path / "raw.h5"
    run_trajectory(model, traj, surface=False, record=raw, header=make_header(model))
    # the same run written raw (as a live writer leaves it before closing)
    live = tmp_path / "live.h5"
    monkeypatch.setattr(writer.SessionWriter.__init__, "__defaults__", (False, False, None))
    run_trajectory(model, traj, surface=False, record=live, header=make_header(model))
    monkeypatch.undo()
    with h5py.File(live, "r") as f:
        assert f["samples/pos_mm"].compression is None
    before = _contents(live)
    raw_size = live.stat().st_size
    size = writer.compact_session(live)
    assert size == live.stat().st_size < raw_size / 2
    with h5py.File(live, "r") as f:
        assert f["samples/pos_mm"].compression == "gzip"
    _same(before, _contents(live))
    assert verify(read_session(live))["ok"]
    with h5py.File(raw, "r") as f:                       # closing compacted it
        assert f["samples/pos_mm"].compression == "gzip"
    # a failure half-way leaves the original file untouched and no debris
    keep = tmp_path / "keep.h5"
    shutil.copy(live, keep)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(writer.os, "replace", boom)
    with pytest.raises(BonesimError, match="disk full.*kept as it was"):
        writer.compact_session(keep)
    monkeypatch.undo()
    _same(before, _contents(keep))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.h5", "live.h5", "raw.h5"]
