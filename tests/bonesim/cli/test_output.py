"""The package version: defined once, in every session header and every JSON
output of the command line (bonesim.cli.output)."""
from __future__ import annotations

import ast
import json
import tomllib
from pathlib import Path

import pytest

import bonesim
from bonesim.cli.main import main
from bonesim.cli.output import VERSION_KEY, print_json, with_version

REPO = Path(__file__).resolve().parents[3]
OLD = REPO / "tests" / "bonesim" / "data" / "sessions" / "phantom2_schema2.h5"


def test_the_version_is_defined_once():
    """pyproject.toml takes the version from bonesim/__init__.py (one place),
    and it moved on from the 0.1.0 every file was stamped with before the
    bundled data was versioned."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert "version" not in project["project"]
    assert "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "bonesim.__version__"}
    tree = ast.parse((REPO / "bonesim" / "__init__.py").read_text())
    literal = [n.value.value for n in tree.body if isinstance(n, ast.Assign)
               and [t.id for t in n.targets if isinstance(t, ast.Name)] == ["__version__"]]
    assert literal == [bonesim.__version__]
    major, minor, patch = map(int, bonesim.__version__.split("."))
    assert (major, minor, patch) > (0, 1, 0)


def test_a_session_header_carries_the_version():
    from bonesim.session.header import make_header
    from bonesim.io.loading import load_model

    h = make_header(load_model("phantom", "cutting-5mm"), input_device="scripted")
    assert h["bonesim_version"] == bonesim.__version__


def test_with_version(capsys):
    v = bonesim.__version__
    assert with_version({"a": 1}) == {VERSION_KEY: v, "a": 1}
    assert list(with_version({"a": 1})) == [VERSION_KEY, "a"]          # first
    assert with_version([1, 2], "cases") == {VERSION_KEY: v, "cases": [1, 2]}
    assert with_version({"a": 1, VERSION_KEY: v}) == {VERSION_KEY: v, "a": 1}
    with pytest.raises(ValueError, match="not this bonesim's"):
        with_version({VERSION_KEY: "0.0.1"})
    with pytest.raises(TypeError, match="object or a list"):
        with_version("text")
    print_json({"x": float("nan")}, default=str)
    assert json.loads(capsys.readouterr().out)[VERSION_KEY] == v


@pytest.mark.parametrize("argv, items", [
    (["cases", "--json"], "cases"),
    (["burrs", "--json"], "burrs"),
    (["case-info", "phantom@1", "--json"], None),
    (["devices", "--json"], None),
    (["sessions", "info", str(OLD), "--json"], None),
    (["replay", "--verify", str(OLD), "--json"], None),
])
def test_json_outputs_say_which_bonesim_made_them(argv, items, capsys):
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out[VERSION_KEY] == bonesim.__version__
    if items:
        assert set(out) == {VERSION_KEY, items} and out[items]


def test_sessions_info_tells_the_recording_version_from_this_one(capsys):
    assert main(["sessions", "info", str(OLD), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["recorded_with"] == "0.1.0" and out[VERSION_KEY] == bonesim.__version__


def _json_prints(text: str) -> list[int]:
    """Lines of ``text`` that print ``json.dumps(...)`` themselves."""
    return [node.lineno for node in ast.walk(ast.parse(text))
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print"
            and node.args and isinstance(node.args[0], ast.Call)
            and getattr(node.args[0].func, "attr", None) == "dumps"]


def test_every_command_prints_json_through_the_one_helper():
    """No command module prints JSON but through print_json (which stamps
    the version); the check finds such a print where one is."""
    assert _json_prints("import json\nx = 1\nprint(json.dumps({}, indent=2))\n") == [3]
    # every module but the helper and the benchmarks' child scripts (their
    # JSON goes to the parent process that measures them, not to a user)
    modules = [p for p in sorted((REPO / "bonesim").rglob("*.py"))
               + sorted((REPO / "metrics").rglob("*.py"))
               if p.name != "output.py" and "bench" not in p.parts]
    found = {str(p.relative_to(REPO)): _json_prints(p.read_text()) for p in modules}
    assert {k: v for k, v in found.items() if v} == {}
