"""``bonesim dataset`` and ``bonesim sessions export`` from the command line:
two runs of the command give identical bytes (HDF5 and folder), the file
holds its provenance and opens with h5py as documented, bad input gives one
line."""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.cli.main import main

REPO = Path(__file__).resolve().parents[3]
ARGS = ["--size", "160x120", "--fps", "2", "--start", "6", "--end", "7", "--stereo", "4",
        "--camera", "fixed", "--zoom", "2", "--no-progress"]


def _cli(*argv):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "bonesim", *map(str, argv)],
                          capture_output=True, text=True, cwd=REPO, env=env, timeout=600)


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for p in files:
        h.update(str(p.relative_to(path.parent if path.is_file() else path)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def made(demo_run, tmp_path_factory):
    """The command run twice, as HDF5 and as a folder: first in this test
    process (which has drawn and compiled other things before), then in a
    fresh process."""
    d = tmp_path_factory.mktemp("cli")
    outs = {}
    for name in ("a.h5", "b.h5", "fa", "fb"):
        extra = ["--normals", "--points", "--rgb", "--depth", "--seg"] if \
            name.endswith("h5") else []
        argv = ["dataset", demo_run, "--out", d / name, *ARGS, *extra, "--json"]
        if name in ("a.h5", "fa"):
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                assert main([str(a) for a in argv]) == 0
            outs[name] = (d / name, json.loads(out.getvalue()))
            continue
        res = _cli(*argv)
        assert res.returncode == 0, res.stderr
        outs[name] = (d / name, json.loads(res.stdout))
    return outs


def _differences(a: Path, b: Path) -> list[str]:
    """What differs between two dataset files: attributes, and per dataset
    the frames and how many values (a readable failure, not two files'
    bytes)."""
    import h5py

    out = []
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        for k in sorted(set(fa.attrs) | set(fb.attrs)):
            if str(fa.attrs.get(k)) != str(fb.attrs.get(k)):
                out.append(f"attribute {k}: {fa.attrs.get(k)!r} != {fb.attrs.get(k)!r}")
        names = []
        fa.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        for n in names:
            if n not in fb:
                out.append(f"{n}: only in {a.name}")
                continue
            x, y = fa[n][()], fb[n][()]
            if x.shape != y.shape:
                out.append(f"{n}: shapes {x.shape} != {y.shape}")
            elif x.tobytes() != y.tobytes():
                d = x != y
                frames = sorted({int(i) for i in np.argwhere(d)[:, 0]}) if d.ndim else []
                diff = np.abs(x.astype(np.float64) - y.astype(np.float64))[d]
                out.append(f"{n}: {int(d.sum())} of {d.size} values differ (frames "
                           f"{frames}, largest difference {np.nanmax(diff, initial=0):g})")
    return out or ["the files' contents are equal: only their layout differs"]


def test_two_runs_of_the_command_give_identical_bytes(made):
    a, b = made["a.h5"][0], made["b.h5"][0]
    same = hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest()
    assert same, "\n".join(_differences(a, b))
    fa, fb = made["fa"][0], made["fb"][0]
    assert _digest(fa) == _digest(fb)
    assert made["a.h5"][1]["frames"] == 2          # 6.0 and 6.5 s: the end excluded


def test_the_file_opens_with_h5py_as_the_readme_shows(made, demo_run):
    import h5py

    from bonesim.session.dataset_spec import file_sha256

    path = made["a.h5"][0]
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "bonesim-dataset" and f.attrs["version"] == 1
        prov = json.loads(f.attrs["provenance"])
        rgb = f["left/rgb"][1]                        # (H, W, 3) uint8, frame 1
        depth = f["left/depth"][1]                    # (H, W) float32 [mm]
        cls = f["left/class"][1]
        k = f["left/camera/K"][1]
        assert rgb.shape == (120, 160, 3) and depth.dtype == np.float32
        assert f["right/rgb"].shape == (2, 120, 160, 3)
        assert f["left/depth"].chunks == (1, 120, 160)
        assert f["left/depth"].compression == "gzip"
        assert f["frames/t_s"][:].tolist() == [6.0, 6.5]
        assert f["frames/removed_voxels"][1] >= f["frames/removed_voxels"][0] > 0
        classes = {c["id"]: c["name"] for c in json.loads(f.attrs["classes"])}
        assert classes[1] == "bone" and classes[200] == "burr"
        assert set(np.unique(cls)) <= set(classes)
        assert k[0, 0] == pytest.approx(60 / np.tan(np.radians(15)))
    assert prov["run_sha256"] == file_sha256(demo_run)
    assert prov["run_name"] == "demo.h5" and prov["options"]["stereo_mm"] == 4.0
    assert prov["bonesim_version"] and prov["case"]["name"] == "phantom"


def test_the_folder_holds_the_same_frames(made):
    from bonesim.session.dataset_io import open_dataset

    with open_dataset(made["a.h5"][0]) as h5, open_dataset(made["fa"][0]) as fo:
        assert len(h5) == len(fo) == 2
        assert fo.attrs["streams"] == ["rgb", "depth", "class", "instance"]
        for i in range(2):
            for eye in ("left", "right"):
                a, b = h5.frame(i, eye), fo.frame(i, eye)
                for s in fo.attrs["streams"]:
                    np.testing.assert_array_equal(a[s], b[s])
                np.testing.assert_allclose(h5.camera(i, eye)["K"], fo.camera(i, eye)["K"])
        for k in ("t_s", "tool_pos_mm", "removed_voxels", "burr", "drill"):
            np.testing.assert_array_equal(h5.frames[k], fo.frames[k])
    index = json.loads((made["fa"][0] / "index.json").read_text())
    assert index["frame_records"][0]["files"]["left"]["depth"] == "left/depth/000000.tiff"


def test_preview_and_errors(demo_run, tmp_path, capsys):
    out = tmp_path / "p.h5"
    code = main(["dataset", str(demo_run), "--out", str(out), "--size", "96x64", "--fps",
                 "1", "--start", "7", "--end", "7.5", "--no-progress",
                 "--preview", str(tmp_path / "p.png")])
    assert code == 0
    from PIL import Image

    with Image.open(tmp_path / "p.png") as im:
        assert im.size[0] >= 3 * 96
    capsys.readouterr()
    for argv, msg in (
            (["dataset", str(tmp_path / "none.h5"), "--out", str(tmp_path / "x.h5")],
             "no such session file"),
            (["dataset", str(demo_run), "--out", str(tmp_path / "y.h5"), "--size", "9x9"],
             "16..8192"),
            (["dataset", str(demo_run), "--out", str(tmp_path / "y.h5"), "--end", "99"],
             "outside the recording"),
            (["dataset", str(demo_run), "--out", str(tmp_path / "nope" / "y.h5")],
             "output folder does not exist"),
            (["dataset", str(demo_run), "--out", str(tmp_path / "y.h5"), "--stereo", "-1"],
             "baseline")):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("bonesim: error: ") and msg in err and err.count("\n") == 1
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    assert main(["dataset", str(demo_run), "--out", str(tmp_path / "full")]) == 2
    assert "not empty" in capsys.readouterr().err


def test_sessions_export_command(demo_run, tmp_path, capsys):
    code = main(["sessions", "export", str(demo_run), str(tmp_path / "case"), "--at", "4",
                 "--json"])
    assert code == 0
    res = json.loads(capsys.readouterr().out)
    assert res["at_s"] == 4.0 and (tmp_path / "case" / "segmentation.seg.nrrd").is_file()
    assert main(["sessions", "export", str(demo_run), str(tmp_path / "case")]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["sessions", "export", str(demo_run), str(tmp_path / "ls"), "--format",
                 "label-stack", "--orientation", "PIR"]) == 0
    assert "remaining" not in capsys.readouterr().err
    assert (tmp_path / "ls" / "planes").is_dir()
