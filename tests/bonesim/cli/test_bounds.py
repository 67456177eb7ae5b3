"""Command-line numbers and every file-taking command against hostile input
(issue 24, rows 5-6): one line naming the file and field (or option), exit
status 2, no traceback. scripts/hostile_inputs.py runs the same inputs and
more (the live window's) as subprocesses under a memory cap."""
from __future__ import annotations

from pathlib import Path

import pytest

from bonesim.cli.main import main

ROOT = Path(__file__).resolve().parents[3]
PHANTOM = (ROOT / "ct_cases" / "phantom" / "case.toml").read_text()
BINARY = bytes(range(256)) * 8
TRAJ = "t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm\n0,0,0,0,0,0,-1,1,6e4\n"


def _one_line(capsys, argv) -> str:
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("bonesim")
    return err


@pytest.mark.parametrize("argv, needle", [
    (["run", "--offscreen", "--frames", "1", "--size", "100000", "100000"], "--size"),
    (["run", "--frames", "-5"], r"\[--frames\]: -5 frames is outside"),
    (["tutor", "serve", "--duration", "nan"], r"\[--duration\]: must be a finite"),
    (["monitor", "127.0.0.1", "--duration", "-1"], r"\[--duration\]: -1 s"),
    (["playback", "x.h5", "--fps", "1e9"], r"\[--fps\]"),
    (["simulate", "--trajectory", "t.csv", "--oversample", "4096"], r"\[--oversample\]"),
    (["cohort", "synth", "--out", "x", "--experts", "1000000000"], r"\[--experts\]"),
])
def test_options_outside_their_bounds(capsys, argv, needle):
    import re

    assert re.search(needle, _one_line(capsys, argv))


def _files(tmp_path):
    case_latin = tmp_path / "latin" / "case.toml"
    case_latin.parent.mkdir()
    case_latin.write_bytes(PHANTOM.replace("Procedural", "Proc\u00e9dural").encode("latin-1"))
    case_bin = tmp_path / "bin" / "case.toml"
    case_bin.parent.mkdir()
    case_bin.write_bytes(BINARY)
    burr_bin = tmp_path / "burr.toml"
    burr_bin.write_bytes(BINARY)
    traj = tmp_path / "t.csv"
    traj.write_text(TRAJ)
    far = tmp_path / "far.csv"
    far.write_text(TRAJ + "0.01,1e300,0,0,0,0,-1,1,6e4\n")
    late = tmp_path / "late.csv"
    late.write_text(TRAJ + "1e12,0,0,0,0,0,-1,1,6e4\n")
    weak = tmp_path / "weak.key"
    weak.write_bytes(b"passwordpassword")
    return {"weak": weak, "case_latin": case_latin, "case_bin": case_bin, "burr_bin": burr_bin,
            "traj": traj, "far": far, "late": late}


@pytest.mark.parametrize("argv, needle", [
    (["case-info", "{case_latin}"], "not a UTF-8 text"),
    (["case-info", "{case_bin}"], "not a UTF-8 text"),
    (["simulate", "--case", "{case_bin}", "--trajectory", "{traj}"], "not a UTF-8"),
    (["simulate", "--burr", "{burr_bin}", "--trajectory", "{traj}"], "burr.toml: not a UTF-8"),
    (["simulate", "--trajectory", "{far}"], r"far.csv \[line 3, column 'x_mm'\]"),
    (["simulate", "--trajectory", "{late}"], r"late.csv .* 1e\+12 s is outside"),
    (["trajectory", "--case", "{case_latin}", "--out", "o.csv"], "not a UTF-8"),
    (["case-export", "{case_bin}", "--format", "nrrd", "out"], "not a UTF-8"),
    (["tutor", "join", "127.0.0.1", "--headless", "--key-file", "{weak}"],
     r"weak.key: key is too weak: about 38 bits"),
    (["monitor", "127.0.0.1", "--key-file", "{weak}"], "key is too weak"),
    (["sessions", "info", "{burr_bin}"], "burr.toml"),
    (["metrics", "run", "{case_bin}"], "case.toml"),
    (["metrics", "cohort", "{traj}", "--participants", "{burr_bin}"], "burr.toml"),
])
def test_every_file_taking_command_refuses_hostile_files_in_one_line(tmp_path, capsys,
                                                                    monkeypatch, argv,
                                                                    needle):
    import re

    monkeypatch.chdir(tmp_path)
    files = {k: str(v) for k, v in _files(tmp_path).items()}
    err = _one_line(capsys, [a.format(**files) for a in argv])
    assert re.search(needle, err), err
