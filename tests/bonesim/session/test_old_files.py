"""Files from before keep working: session files written by older bonesim
open, play back, replay bit for bit and score, rebuilt from the bundled case
versions their recorded model hashes find.

The fixtures (``tests/bonesim/data/sessions/README.md`` says which commit and
command made each) were recorded by the old code itself: a schema-1 file on
the first phantom (``phantom@1``, the generator of commit 15854c3) and a
schema-2 file on the phantom before the posterior fossa was closed
(``phantom@2``). Their headers name manifest paths that no longer exist.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from bonesim.cli.main import main
from bonesim.engine import events
from bonesim.session.playback import Player
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify

DATA = Path(__file__).resolve().parents[1] / "data" / "sessions"
#: file -> (schema, case version, removals the old code recorded)
OLD = {"phantom1_schema1.h5": (1, "phantom@1", 1385),
       "phantom2_schema2.h5": (2, "phantom@2", 1329)}


@pytest.fixture(scope="module", params=sorted(OLD))
def old(request):
    """(path, schema, version, removals, session read and rebuilt once)."""
    path = DATA / request.param
    schema, version, n = OLD[request.param]
    s = read_session(path)
    s.burr_models()                               # finds the version
    return path, schema, version, n, s


def test_the_fixtures_are_what_the_old_code_wrote(old):
    path, schema, _, n, _ = old
    with h5py.File(path, "r") as f:
        assert int(f.attrs["schema"]) == schema
        header = json.loads(f.attrs["header"])
    assert header["bonesim_version"] == "0.1.0"
    assert header["case"]["name"] == "phantom" and header["input"] == "scripted"
    # recorded in a worktree that is gone: the manifest path does not exist
    assert not Path(header["case"]["path"]).exists()
    assert path.stat().st_size < 300_000


def test_an_old_file_opens_on_the_version_it_was_recorded_on(old):
    path, schema, version, n, s = old
    assert s.schema == schema and s.complete and s.damage is None
    assert s.case_version == version
    assert int((s.tissue["kind"] == events.REMOVED).sum()) == n
    assert s.duration_s == pytest.approx(4.0)
    # the model rebuilt is the recorded one, and today's phantom is not it
    from bonesim.session.header import model_sha256

    m = s.load_model()
    assert model_sha256(m) == s.header["model_sha256"][0]
    assert m.case.volume.generation == int(version.split("@")[1])


def test_an_old_file_replays_bit_for_bit(old):
    path, _, _, n, s = old
    report = verify(s)
    assert report["ok"] and report["identical"], report
    assert report["removals_recorded"] == report["removals_replayed"] == n


def test_an_old_file_plays_back(old):
    """Headless playback (the Player the window and the video export draw
    from): the tissue at the end is the replayed one; halfway, fewer voxels
    are gone, the tool stands where the recording had it."""
    _, _, _, n, s = old
    out = replay(s)
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    gone = p.grid.density == 0
    np.testing.assert_array_equal(gone, out["state"].grid.density == 0)
    p.seek(0.0)
    before = int((p.grid.density == 0).sum())
    assert int(gone.sum()) - before == n                 # every removal shown
    p.seek(s.duration_s / 2)
    half = int((p.grid.density == 0).sum())
    assert before < half < int(gone.sum())
    frame = p.frame()
    assert frame.voxels_removed == half - before
    i = int(np.searchsorted(s.samples["t_s"], frame.t_s, side="right")) - 1
    np.testing.assert_allclose(frame.pos_mm, s.samples["pos_mm"][i])


def test_an_old_file_scores(old):
    from metrics.run import run_metrics

    path, _, version, n, s = old
    res = run_metrics(s)
    assert res["run"]["removed_voxels"] == n and not res["run"]["damaged"]
    vis = res["visibility"]
    assert vis["removals"] == n and vis["visible_fraction"] == 1.0
    assert vis["live_mismatches"] == 0      # judged from the camera it was recorded with
    a = res["assessment"]
    assert a["case"] == "phantom" and 0 < a["total"] <= a["max_total"]
    assert a["removed_mm3"] == pytest.approx(n * 0.5 ** 3)


def test_old_files_through_the_cli(old, capsys):
    path, _, version, n, _ = old
    assert main(["replay", "--verify", str(path)]) == 0
    assert "identical" in capsys.readouterr().out
    assert main(["metrics", "run", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["run"]["removed_voxels"] == n


def test_a_recorded_path_that_now_holds_another_version(tmp_path):
    """A file recorded on an install or checkout whose case was since updated
    in place names a manifest that exists but builds another model: the
    kept versions are tried all the same (schema 1 and 2 headers carry no
    checksum, so the copy's header may be edited to say so)."""
    from bonesim.io.case import cases_dir

    checkout = tmp_path / "checkout"
    checkout.mkdir()
    shutil.copy(cases_dir() / "phantom" / "case.toml", checkout / "case.toml")
    for manifest in (cases_dir() / "phantom" / "case.toml", checkout / "case.toml"):
        copy = tmp_path / "moved.h5"
        shutil.copy(DATA / "phantom2_schema2.h5", copy)
        with h5py.File(copy, "r+") as f:
            header = json.loads(f.attrs["header"])
            header["case"]["path"] = str(manifest)
            f.attrs["header"] = json.dumps(header)
        s = read_session(copy)
        s.burr_models()
        assert s.case_version == "phantom@2", manifest
    assert verify(s)["ok"]
