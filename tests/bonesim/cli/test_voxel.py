"""``--voxel-mm`` (bonesim.cli.voxel): on every command that loads a case."""
from __future__ import annotations

import argparse

import pytest

from bonesim.cli.main import build_parser
from bonesim.cli.voxel import apply_voxel_mm
from bonesim.io.case import load_case


@pytest.mark.parametrize("cmd", ["case-info phantom", "case-export phantom out --format nrrd",
                                 "simulate --trajectory t.csv", "trajectory --out t.csv",
                                 "demo", "run"])
def test_voxel_mm_on_the_commands_that_load_a_case(cmd):
    p = build_parser()
    argv = cmd.split()
    assert p.parse_args(argv).voxel_mm is None                  # the manifest's
    assert p.parse_args(argv + ["--voxel-mm", "native"]).voxel_mm == "native"
    assert p.parse_args(argv + ["--voxel-mm", "0.25"]).voxel_mm == 0.25


def test_apply_voxel_mm_loads_the_case_only_when_asked():
    args = argparse.Namespace(case="phantom", voxel_mm=None)
    apply_voxel_mm(args)
    assert args.case == "phantom"                               # passed on by name
    args = argparse.Namespace(case="phantom", voxel_mm=2.0)
    apply_voxel_mm(args)
    assert args.case == load_case("phantom").with_voxel_mm(2.0)
    assert args.case.volume.voxel_mm == 2.0
