"""The bonesim command line: help, JSON outputs, headless runs and clear errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bonesim.cli.main import build_parser, main

REPO = Path(__file__).resolve().parents[3]
SUBCOMMANDS = ["cases", "case-info", "case-export", "burrs", "simulate", "trajectory",
               "demo", "bench"]


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("cmd", SUBCOMMANDS)
def test_every_subcommand_has_help(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert "usage: bonesim " + cmd in capsys.readouterr().out


def test_parser_lists_all_subcommands():
    text = build_parser().format_help()
    for cmd in SUBCOMMANDS:
        assert cmd in text


def test_cases_and_burrs_json(capsys):
    code, out, _ = run_cli(capsys, "cases", "--json")
    assert code == 0 and "phantom" in [c["name"] for c in json.loads(out)["cases"]]
    code, out, _ = run_cli(capsys, "burrs", "--json")
    names = [b["name"] for b in json.loads(out)["burrs"]]
    assert code == 0
    assert {f"cutting-{d}mm" for d in range(1, 8)} <= set(names)
    assert {f"diamond-{d}mm" for d in range(1, 6)} <= set(names)


def test_case_info_by_name_and_by_path(capsys):
    code, out, _ = run_cli(capsys, "case-info", "phantom", "--json")
    info = json.loads(out)
    assert code == 0 and info["voxel_mm"] == 0.5 and info["counts"]["facial_nerve"] > 0
    manifest = info["manifest"]
    code, out2, _ = run_cli(capsys, "case-info", manifest, "--json")
    assert code == 0 and json.loads(out2)["counts"] == info["counts"]


@pytest.mark.parametrize("argv, needle", [
    (["case-info", "no-such-case"], "no-such-case"),
    (["simulate", "--trajectory", "/nonexistent/traj.csv"], "traj.csv"),
    (["simulate", "--burr", "cutting-99mm", "--trajectory", "{traj}"], "cutting-99mm"),
    (["bench", "--only", "no_such_bench"], "no_such_bench"),
    (["simulate", "--trajectory", "{traj_burr}"], "--extra-burr"),
])
def test_bad_input_is_one_clear_line(argv, needle, capsys, tmp_path):
    traj = tmp_path / "t.csv"
    traj.write_text("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm\n"
                    "0,0,0,0,0,0,-1,0,0\n0.01,0,0,0,0,0,-1,0,0\n")
    burr = tmp_path / "b.csv"
    burr.write_text("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm,burr\n"
                    "0,0,0,0,0,0,-1,0,0,0\n0.01,0,0,0,0,0,-1,0,0,2\n")
    argv = [a.replace("{traj}", str(traj)).replace("{traj_burr}", str(burr)) for a in argv]
    code, out, err = run_cli(capsys, *argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bonesim: error:") and needle in lines[0]
    assert "Traceback" not in err


def test_trajectory_then_simulate_with_check(capsys, tmp_path):
    traj = tmp_path / "demo.csv"
    code, out, _ = run_cli(capsys, "trajectory", "--case", "phantom", "--kind",
                           "demo-mastoidectomy", "--out", str(traj))
    assert code == 0 and traj.is_file()
    # keep the first 4 s so the test stays quick
    lines = traj.read_text().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) <= 4.0]
    short = tmp_path / "short.csv"
    short.write_text("\n".join(keep) + "\n")
    code, out, _ = run_cli(capsys, "simulate", "--case", "phantom", "--burr", "cutting-5mm",
                           "--trajectory", str(short), "--out", str(tmp_path / "run"),
                           "--check", "--json")
    s = json.loads(out)
    assert code == 0
    for key in ("voxels_removed", "removed_by_structure", "injuries", "vertices",
                "triangles", "force_n", "haptic_step_us"):
        assert key in s
    assert s["surface_consistent"] is True
    assert s["voxels_removed"] > 0 and s["force_n"]["max"] > 0
    assert s["haptic_step_us"]["p50"] > 0
    assert Path(s["mesh"]).is_file() and Path(s["summary"]).is_file()
    # the same path with a burr change half-way, recorded: replays bit for bit
    import dataclasses

    import numpy as np

    from bonesim.io.trajectory import read_trajectory, write_trajectory

    tr = read_trajectory(short)
    write_trajectory(tmp_path / "two.csv", dataclasses.replace(
        tr, burr=(np.arange(len(tr)) >= len(tr) // 2).astype(np.uint8)))
    h5 = tmp_path / "two.h5"
    code, out, err = run_cli(capsys, "simulate", "--trajectory", str(tmp_path / "two.csv"),
                             "--extra-burr", "diamond-3mm", "--record", str(h5))
    assert code == 0, err
    from bonesim.session.reader import read_session

    rec = read_session(h5)
    assert [b["name"] for b in rec.header["burrs"]] == ["cutting-5mm", "diamond-3mm"]
    assert rec.samples["burr"][0] == 0 and rec.samples["burr"][-1] == 1
    code, out, err = run_cli(capsys, "replay", str(h5), "--verify")
    assert code == 0, err


def test_import_is_light():
    code = ("import sys, bonesim, bonesim.engine.model, bonesim.cli.main; "
            "bad = [m for m in ('vtk', 'pyvista', 'sounddevice', 'usb', 'hid') "
            "if m in sys.modules]; print(bad)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, check=True)
    assert res.stdout.strip() == "[]"


def test_installed_package_ships_its_data(tmp_path):
    """Outside the source tree, the installed package finds its cases and burrs
    (the editable install of scripts/setup.sh maps the package to this tree)."""
    from importlib.metadata import distribution
    assert distribution("bonesim").version
    code = ("import bonesim, ct_cases, burrs, metrics, pathlib; "
            "from bonesim.io.case import load_case; from bonesim.io.burrs import load_burr; "
            "from bonesim.engine.materials import load_materials; "
            "c = load_case('phantom'); b = load_burr('diamond-2mm'); load_materials(); "
            "print(c.name, b.name)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["phantom", "diamond-2mm"]


def test_every_data_file_is_in_the_package_data():
    """A wheel ships only the data files pyproject.toml's package-data names:
    every non-Python file in the shipped packages matches one of its patterns."""
    import fnmatch
    import tomllib
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = cfg["package-data"]
    unshipped = []
    for top in ("bonesim", "ct_cases", "burrs", "metrics"):
        for f in (REPO / top).rglob("*"):
            if (not f.is_file() or f.suffix in (".py", ".pyc", ".nbi", ".nbc")
                    or "__pycache__" in f.parts):
                continue
            package = ".".join(f.parent.relative_to(REPO).parts)
            names = patterns.get("*", []) + patterns.get(package, [])
            if not any(fnmatch.fnmatch(f.name, pat) for pat in names):
                unshipped.append(str(f.relative_to(REPO)))
    assert unshipped == []


def test_simulate_rejects_bad_trajectory_rows(capsys, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm\n"
                   "0,0,0,0,0,0,-1,0,0\n0.01,0,0,abc,0,0,-1,0,0\n")
    code, _, err = run_cli(capsys, "simulate", "--trajectory", str(bad))
    assert code == 2 and "bad.csv" in err and "z_mm" in err


def test_run_records_only_when_asked():
    p = build_parser()
    assert p.parse_args(["run"]).record is None
    assert p.parse_args(["run", "--record"]).record == ""
    assert p.parse_args(["run", "--record", "x.h5"]).record == "x.h5"


def test_voxel_mm_overrides_the_manifest(capsys, tmp_path):
    code, out, _ = run_cli(capsys, "case-info", "phantom", "--json", "--voxel-mm", "1")
    info = json.loads(out)
    assert code == 0 and info["voxel_mm"] == 1.0 and info["grid"] == [52, 52, 52]
    # the phantom has no source: native keeps its manifest's 0.5 mm
    code, out, _ = run_cli(capsys, "case-info", "phantom", "--json", "--voxel-mm", "native")
    assert code == 0 and json.loads(out)["voxel_mm"] == 0.5
    code, out, _ = run_cli(capsys, "case-export", "phantom", "--format", "label-stack",
                           str(tmp_path / "st"), "--voxel-mm", "2")
    assert code == 0 and "export of case 'phantom'" in out
    assert len(list((tmp_path / "st" / "planes").glob("*.png"))) == 26
    with pytest.raises(SystemExit) as e:
        main(["case-info", "phantom", "--voxel-mm", "fine"])
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert "--voxel-mm: must be a number of mm" in err and "'fine'" in err


def test_a_run_at_another_voxel_replays_at_it(capsys, tmp_path):
    """--voxel-mm is part of the run: the recording replays at that voxel."""
    t = [i * 0.01 for i in range(81)]
    rows = ["t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm"]
    rows += [f"{ti},{24.0 - 12.0 * ti},0.9,1.0,-1,0,0,1,60000" for ti in t]
    traj = tmp_path / "in.csv"
    traj.write_text("\n".join(rows) + "\n")
    h5 = tmp_path / "coarse.h5"
    code, out, err = run_cli(capsys, "simulate", "--trajectory", str(traj), "--voxel-mm", "1",
                             "--record", str(h5), "--json")
    assert code == 0, err
    assert json.loads(out)["voxels_removed"] > 0
    from bonesim.session.reader import read_session

    assert read_session(h5).header["voxel_mm"] == 1.0
    code, out, err = run_cli(capsys, "replay", str(h5), "--verify")
    assert code == 0, err
