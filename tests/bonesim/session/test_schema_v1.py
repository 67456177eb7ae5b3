"""Version-1 session files (before the tissue-event stream) read, replay and play back.

``data/sessions/schema1.h5`` was written by bonesim's schema-1 recorder
(``data/sessions/make_schema1.py``, run on the last schema-1 commit): 1.5 s of
the demo plan on the phantom with a case reset at 0.7 s, a burr change at
1.1 s and a contact with a nerve at 1.3 s.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from bonesim.engine import events
from bonesim.cli.main import main
from bonesim.session.playback import Player
from bonesim.session.schema import SCHEMA_VERSION
from bonesim.session.replay import replay, verify
from bonesim.session.reader import read_session, repair_session
from bonesim.session.schema_v1 import GROUPS_V1

V1 = Path(__file__).resolve().parents[1] / "data" / "sessions" / "schema1.h5"


def test_the_fixture_is_schema_1():
    with h5py.File(V1, "r") as f:
        assert int(f.attrs["schema"]) == 1
        assert set(GROUPS_V1) <= set(f) and "tissue" not in f
        n_rem = len(f["removals/t_s"])
        names = [n.decode() for n in f["events/name"][:]]
    assert n_rem > 1000 and {"reset", "burr"} <= set(names)


def test_a_v1_file_migrates_to_the_tissue_stream():
    s = read_session(V1)
    assert s.schema == 1 and s.complete
    k = s.tissue["kind"]
    with h5py.File(V1, "r") as f:
        n_rem, n_inj = len(f["removals/t_s"]), len(f["injuries/t_s"])
        np.testing.assert_array_equal(s.removals["ijk"], f["removals/ijk"][:])
        np.testing.assert_array_equal(s.removals["visible"], f["removals/visible"][:])
    assert (k == events.REMOVED).sum() == n_rem and n_inj == 1
    assert [events.KIND_NAMES[x] for x in k[k >= events.RESET]] == ["reset", "burr"]
    assert (np.diff(s.tissue["t_s"]) >= 0).all()
    assert (s.tissue["body"] == 0).all()
    assert s.injuries["kind"][0] == events.INJURY_CONTACT
    # reset and burr rows became tissue events; the other ui events stay
    assert not [e for e in s.events if e[1] in ("reset", "burr")]


def test_a_v1_file_replays_bit_for_bit_and_plays_back():
    """The fixture was recorded on the phantom's generation 2; it replays on
    the kept ``phantom@2``, found by its recorded hashes."""
    s = read_session(V1)
    report = verify(s)
    assert report["ok"], report
    assert s.case_version == "phantom@2"
    assert report["events_recorded"] == report["events_replayed"] > 1000
    assert main(["replay", str(V1), "--verify"]) == 0
    out = replay(s)
    p = Player(s, surface=False)
    p.seek(s.duration_s)
    np.testing.assert_array_equal(p.grid.density == 0, out["state"].grid.density == 0)
    assert p.frame().epoch == 1


def test_repair_writes_a_v1_file_in_the_current_schema(tmp_path):
    out = tmp_path / "v3.h5"
    s2 = repair_session(V1, out)
    assert s2.schema == SCHEMA_VERSION == 4 and s2.checksums and s2.header_ok
    s1 = read_session(V1)
    for name in s1.tissue:
        np.testing.assert_array_equal(s1.tissue[name], s2.tissue[name], err_msg=name)
    assert verify(s2)["ok"]
