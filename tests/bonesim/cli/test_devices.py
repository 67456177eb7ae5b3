"""The device commands' help, and `import bonesim.cli.main` still imports no
device SDK."""
from __future__ import annotations

import pytest

from bonesim.cli.main import build_parser, main


@pytest.mark.parametrize("cmd", ["devices", "calibrate"])
def test_device_commands_have_help(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert "usage: bonesim " + cmd in capsys.readouterr().out


def test_run_takes_a_device_and_a_pedal():
    args = build_parser().parse_args(["run", "--device", "touch", "--pedal"])
    assert args.device == "touch" and args.pedal == "pedal"
    args = build_parser().parse_args(["run"])
    assert args.device == "mouse" and args.pedal is None
    args = build_parser().parse_args(["run", "--pedal", "adu100-handle"])
    assert args.pedal == "adu100-handle"
