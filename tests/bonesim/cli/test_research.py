"""The research commands' arguments (bonesim.cli.research)."""
from __future__ import annotations

import subprocess
import sys

from bonesim.cli.main import build_parser


def test_building_the_cli_imports_no_metrics():
    code = ("import sys, bonesim.cli.main as m; m.build_parser(); "
            "print(sorted(k for k in sys.modules if k == 'metrics' or k.startswith('metrics.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_research_commands_parse():
    p = build_parser()
    a = p.parse_args(["metrics", "cohort", "runs/", "--participants", "p.csv", "--workers",
                      "3", "--out", "t.parquet"])
    assert (a.sessions, a.participants, a.workers, a.out) == ("runs/", "p.csv", 3, "t.parquet")
    a = p.parse_args(["metrics", "run", "x.h5", "--expert", "e1.h5", "--expert", "e2.h5"])
    assert a.expert == ["e1.h5", "e2.h5"] and not a.json
    a = p.parse_args(["cohort", "synth", "--out", "d", "--experts", "2"])
    assert (a.experts, a.novices, a.duration) == (2, 6, 180.0)


def test_research_code_is_reached_by_name_and_missing_research_is_one_line(monkeypatch):
    import pytest

    from bonesim.cli.research import research_module
    from bonesim.errors import BonesimError

    assert research_module("metrics.assessment", "bonesim assess").__name__ == \
        "metrics.assessment"
    monkeypatch.setitem(sys.modules, "metrics.no_such", None)     # import fails
    with pytest.raises(BonesimError) as e:
        research_module("metrics.no_such", "bonesim assess")
    assert "\n" not in str(e.value) and "bonesim assess needs the research package" in str(e.value)
