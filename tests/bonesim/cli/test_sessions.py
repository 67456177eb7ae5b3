"""``bonesim sessions`` commands (bonesim.cli.sessions)."""
from __future__ import annotations

import json

import bonesim
from bonesim.cli.main import main


def test_list_before_the_first_recording(tmp_path, monkeypatch, capsys):
    """No recording yet: the default folder does not exist, and that is no error;
    a folder named on the command line still has to exist."""
    monkeypatch.setenv("BONESIM_SESSIONS", str(tmp_path / "not-yet"))
    assert main(["sessions", "list"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("no sessions yet") and str(tmp_path / "not-yet") in out
    assert main(["sessions", "list", str(tmp_path / "nowhere")]) == 2
    assert "no such sessions folder" in capsys.readouterr().err
    (tmp_path / "not-yet").mkdir()
    assert main(["sessions", "list"]) == 0
    assert capsys.readouterr().out.startswith("no sessions in")


def test_list_json_before_the_first_recording(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("BONESIM_SESSIONS", str(tmp_path / "not-yet"))
    assert main(["sessions", "list", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"bonesim_version": bonesim.__version__,
                                                   "sessions": []}
