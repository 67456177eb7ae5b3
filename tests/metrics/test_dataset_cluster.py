"""Datasets of many runs on the Dask cluster (metrics.dataset_cluster): one
task per run, progress, the same file as the single-run command, a broken
run reported in one line while the others are rendered."""
from __future__ import annotations

import shutil

import pytest

from bonesim.session.dataset_spec import DatasetOptions
from metrics.dataset_cluster import output_path, render_many

OPTS = DatasetOptions(size=(64, 48), fps=2.0, start=0.5, end=1.5, camera="fixed")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from tests.bonesim.dataset_runs import demo_part, record

    d = tmp_path_factory.mktemp("many")
    record(d / "r1.h5", demo_part(0.0, 2.0))
    shutil.copy(d / "r1.h5", d / "r2.h5")
    (d / "broken.h5").write_bytes(b"not a session")
    return d


def test_many_runs_one_task_each_same_bytes_as_one_run(runs, tmp_path, gl_probe):
    from bonesim.render.dataset import make_dataset

    seen = []
    res = render_many(runs, tmp_path / "out", OPTS, workers=1,
                      progress=lambda done, n: seen.append((done, n)))
    assert res["cluster"] == "LocalCluster" and res["failed"] == 1, res["runs"]
    assert seen[-1] == (3, 3) and len(seen) == 3
    by = {r["file"].split("/")[-1]: r for r in res["runs"]}
    assert "broken.h5" in by["broken.h5"]["error"] and "\n" not in by["broken.h5"]["error"]
    for name in ("r1.h5", "r2.h5"):
        assert by[name]["frames"] == 2
        assert output_path(tmp_path / "out", name).is_file()
    one = make_dataset(runs / "r1.h5", tmp_path / "one.h5", OPTS)
    assert one["frames"] == 2
    a = (tmp_path / "one.h5").read_bytes()
    assert a == output_path(tmp_path / "out", "r1.h5").read_bytes()
    # the provenance names the run by its bytes: r2 is a copy of r1
    assert a == output_path(tmp_path / "out", "r2.h5").read_bytes().replace(b"r2.h5", b"r1.h5")
    # rendering again into the same folder refuses each existing output
    again = render_many(runs / "r*.h5", tmp_path / "out", OPTS, workers=1)
    assert again["failed"] == 2 and all("exists" in r["error"] for r in again["runs"])


@pytest.fixture(scope="module")
def gl_probe():
    from bonesim.render.gl import select_backend

    return select_backend(offscreen=True)
