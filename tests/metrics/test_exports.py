"""Exports with provenance (metrics.exports, metrics.provenance): the
visibility NRRD reopens on the case's grid, the removals Parquet and the
cohort CSVs carry where they came from."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bonesim.engine import events


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from metrics.synth import synth_cohort

    d = tmp_path_factory.mktemp("exp")
    (path,) = synth_cohort(d, 0, 1, seed=9, duration_s=6.0)
    return d, path


def test_visibility_nrrd_and_removals_parquet_reopen_on_the_case_grid(run, tmp_path):
    import nrrd
    import pyarrow.parquet as pq

    from bonesim.session.reader import read_session
    from metrics.exports import PROVENANCE_KEY, export_run
    from metrics.visibility import visibility

    d, path = run
    out = export_run(path, tmp_path / "x", participants=d / "participants.csv",
                     command="bonesim metrics export test")
    s = read_session(path)
    h = s.header
    data, hdr = nrrd.read(out["visibility"], index_order="F")
    assert data.shape == tuple(h["shape"]) and data.dtype == np.uint8
    np.testing.assert_allclose(hdr["space origin"], h["origin_mm"])
    np.testing.assert_allclose(hdr["space directions"], np.eye(3) * h["voxel_mm"])
    assert hdr["space"] == "left-posterior-superior"
    # every drilled voxel is 1 (visible) or 2 (hidden), as the recomputed verdicts say
    kinds = np.asarray(s.tissue["kind"])
    drilled = events.drilled(s.tissue)[kinds == events.REMOVED]
    ijk = np.asarray(s.removals["ijk"])[drilled]
    vis = visibility(s).visible[drilled]
    assert len(ijk) > 20 and set(np.unique(data)) <= {0, 1, 2}
    last = {tuple(v): int(x) for v, x in zip(ijk, vis)}         # the last verdict wins
    for v, x in last.items():
        assert data[v] == (1 if x == 1 else 2)
    assert np.count_nonzero(data) == len(last)
    prov = json.loads(hdr[PROVENANCE_KEY])
    assert prov["case"] == [{"name": h["case"]["name"], "sha256": h["case"]["sha256"]}]
    assert prov["burrs"][0]["sha256"] == h["burrs"][0]["sha256"]
    assert prov["command"] == "bonesim metrics export test"
    assert prov["synthesis"]["seed"] == 9 and len(prov["participants_sha256"]) == 64
    tab = pq.read_table(out["removals"])
    assert json.loads(tab.schema.metadata[PROVENANCE_KEY.encode()]) == prov
    df = tab.to_pandas()
    assert len(df) == len(ijk) and (df[["i", "j", "k"]].to_numpy() == ijk).all()
    assert {"t_s", "visible", "force_n", "speed_rpm", "tool_mm_s",
            "dist_chorda_tympani_mm", "dist_facial_nerve_mm"} <= set(df.columns)
    assert (df["dist_chorda_tympani_mm"] >= 0).all() and (df["force_n"] >= 0).all()


def test_provenance_hashes_the_participants_file(tmp_path):
    from metrics.provenance import file_sha256, provenance

    p = tmp_path / "p.csv"
    p.write_text("id,group,instructor_score\n")
    a = provenance([], p, command="x")
    p.write_text("id,group,instructor_score\nA,expert,4\n")
    b = provenance([], p, command="x")
    assert a["participants_sha256"] != b["participants_sha256"] == file_sha256(p)
    assert a["synthesis"] is None and provenance([], p, seed=3)["synthesis"] == {"seed": 3}
    assert file_sha256(tmp_path / "missing") is None
