"""The package's layering: the import-linter contracts in pyproject.toml hold,
no import cycle exists in bonesim and metrics (imports inside functions
included), and every import made from a string is listed in pyproject.toml
and resolves."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[2]


def _graph():
    import grimp                           # comes with import-linter (test extras)

    sys.path.insert(0, str(ROOT))          # the source tree, not an installed copy
    try:
        return grimp.build_graph("bonesim", "metrics", include_external_packages=False,
                                 cache_dir=None)
    finally:
        sys.path.remove(str(ROOT))


def strongly_connected(adj: dict) -> list[list[str]]:
    """Tarjan's strongly connected components of size > 1 (import cycles)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in adj[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(adj):
        if v not in index:
            visit(v)
    return out


def test_strongly_connected_finds_a_planted_cycle():
    adj = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"d"}}
    assert strongly_connected(adj) == [["a", "b", "c"]]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    g = _graph()
    adj = {m: set(g.find_modules_directly_imported_by(m)) for m in g.modules}
    cycles = strongly_connected(adj)
    detail = []
    for comp in cycles:
        edges = [f"{a} -> {b}" for a in comp for b in sorted(adj[a]) if b in comp]
        detail.append(", ".join(edges))
    assert not cycles, "import cycles: " + " | ".join(detail)


def test_import_linter_contracts_hold():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert exe is not None, "lint-imports missing: scripts/setup.sh --test installs it"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([exe, "--no-cache"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "0 broken" in res.stdout


def test_every_module_declares_all_and_it_names_real_things():
    import importlib
    import pkgutil

    sys.path.insert(0, str(ROOT))
    try:
        import bonesim

        missing, wrong = [], []
        for info in pkgutil.walk_packages(bonesim.__path__, "bonesim."):
            if info.name.endswith("__main__"):
                continue
            mod = importlib.import_module(info.name)
            names = getattr(mod, "__all__", None)
            if names is None:
                if not info.ispkg:
                    missing.append(info.name)
                continue
            wrong += [f"{info.name}.{n}" for n in names if not hasattr(mod, n)]
    finally:
        sys.path.remove(str(ROOT))
    assert not missing, f"modules without __all__: {missing}"
    assert not wrong, f"__all__ names that do not exist: {wrong}"


# --- the layout (added with the package in layers) -------------------------

#: Layers, lowest first (pyproject.toml's "The layers" contract, read below).
TOP_LEVEL = {"__init__", "__main__", "errors", "tomlfile", "progress", "resources"}


def _contracts():
    import tomllib

    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["importlinter"]["contracts"]


def test_every_subpackage_is_a_declared_layer():
    layers = next(c for c in _contracts() if c["type"] == "layers")["layers"]
    declared = {m.strip() for layer in layers for m in layer.split("|")}
    pkgs = {f"bonesim.{p.name}" for p in (ROOT / "bonesim").iterdir()
            if (p / "__init__.py").exists()}
    assert pkgs == declared, (sorted(pkgs - declared), sorted(declared - pkgs))


def test_the_top_level_stays_small():
    mods = {p.stem for p in (ROOT / "bonesim").glob("*.py")}
    assert mods <= TOP_LEVEL, f"top-level modules outside the layers: {sorted(mods - TOP_LEVEL)}"


def test_tests_mirror_the_package():
    """tests/bonesim/<layer>/test_x.py sits beside a bonesim/<layer>/ package,
    and every layer's test folder is a package (so ``io`` never shadows the
    standard library's)."""
    here = ROOT / "tests" / "bonesim"
    for d in sorted(p for p in here.iterdir() if p.is_dir() and p.name not in
                    ("data", "__pycache__")):
        assert (ROOT / "bonesim" / d.name / "__init__.py").exists(), d
        assert (d / "__init__.py").exists(), d
    stray = sorted(p.name for p in here.glob("test_*.py")
                   if p.stem != "test_layers" and p.stem[5:] not in TOP_LEVEL)
    assert not stray, f"tests outside the layers' folders: {stray}"


def test_the_data_folder_is_found_from_every_layer():
    from bonesim.resources import data_path

    assert data_path("materials.toml").is_file()
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "bonesim").rglob("*.py")
            if '/ "data"' in p.read_text() and p.name != "resources.py"]
    assert not hits, f"data paths not through bonesim.resources.data_path: {hits}"


# --- imports made from strings ----------------------------------------------
#: Calls that import what a string literal names: function -> (index of the
#: module argument, index of the attribute argument or None).
STRING_IMPORT_CALLS = {"import_module": (0, None), "__import__": (0, None), "_lazy": (0, 1),
                       "ByName": (0, None), "_by_name": (1, None), "research_module": (0, None)}
#: Wrappers of ``_lazy`` with a fixed module: function -> module.
LAZY_WRAPPERS = {"_tutor": "bonesim.cli.tutor"}


def string_imports(source: str) -> tuple[set, set]:
    """The string imports in a module's ``source``: ``(targets, dynamic)``,
    targets ``"module"`` or ``"module:attribute"`` named by literals, and the
    names of the calls that import a name computed at run time."""
    import ast

    targets, dynamic = set(), set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)

        def lit(i):
            a = node.args[i] if i is not None and i < len(node.args) else None
            return a.value if isinstance(a, ast.Constant) and isinstance(a.value, str) else None

        if name in LAZY_WRAPPERS:
            if lit(0):
                targets.add(f"{LAZY_WRAPPERS[name]}:{lit(0)}")
            continue
        if name not in STRING_IMPORT_CALLS:
            continue
        i, j = STRING_IMPORT_CALLS[name]
        mod = lit(i)
        if mod is None:
            dynamic.add(name)
        else:
            targets.add(mod if lit(j) is None else f"{mod}:{lit(j)}")
    return targets, dynamic


def _listed():
    import tomllib

    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["bonesim"]


def _resolve(target: str):
    import importlib

    mod, _, attr = target.partition(":")
    m = importlib.import_module(mod)
    return getattr(m, attr) if attr else m


def _table_targets(owner: str, table) -> list[str]:
    """Dotted names in a table of :data:`string-import-tables`: values
    ``ByName`` (``ref``), a module name (the key is the attribute; relative
    to ``owner`` without a dot), or tuples ``(module or None, function or
    description, ...)``."""
    out = []
    rows = table.items() if isinstance(table, dict) else enumerate(table)
    for key, v in rows:
        if hasattr(v, "ref"):
            out.append(v.ref)
        elif isinstance(v, str):
            out.append(f"{v if '.' in v else owner + '.' + v}:{key}")
        elif isinstance(v, tuple) and v and isinstance(v[0], str):
            fn = v[1] if len(v) > 1 and isinstance(v[1], str) and v[1].isidentifier() else ""
            out.append(f"{v[0]}:{fn}" if fn else v[0])
    return out


def test_the_string_import_scan_finds_planted_imports():
    src = ("import importlib\n"
           "def f(m):\n"
           "    importlib.import_module('metrics.x')\n"
           "    _lazy('bonesim.cli.sessions', 'cmd_replay')\n"
           "    __import__(m)\n")
    assert string_imports(src) == ({"metrics.x", "bonesim.cli.sessions:cmd_replay"},
                                   {"__import__"})


def test_every_string_import_is_listed_and_resolves():
    listed = _listed()
    found, dynamic = {}, {}
    for p in sorted([*(ROOT / "bonesim").rglob("*.py"), *(ROOT / "metrics").rglob("*.py")]):
        mod = ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        targets, dyn = string_imports(p.read_text())
        if targets:
            found[mod] = sorted(targets)
        if dyn:
            dynamic[mod] = sorted(dyn)
    want = {k: sorted(v) for k, v in listed["string-imports"].items()}
    assert found == want, ("string imports in the code and in pyproject.toml's "
                           "[tool.bonesim.string-imports] differ", found, want)
    allowed = set(listed["string-import-tables"]) | set(listed["string-import-dispatchers"])
    assert set(dynamic) <= allowed, ("imports of computed names outside the listed tables "
                                     "and dispatchers", sorted(set(dynamic) - allowed))
    sys.path.insert(0, str(ROOT))
    try:
        import importlib

        broken = []
        for importer, targets in want.items():
            for t in targets:
                try:
                    _resolve(t)
                except (ImportError, AttributeError) as exc:
                    broken.append(f"{importer} -> {t}: {exc}")
        tables = 0
        for owner, name in listed["string-import-tables"].items():
            table = getattr(importlib.import_module(owner), name)
            for t in _table_targets(owner, table):
                tables += 1
                try:
                    _resolve(t)
                except (ImportError, AttributeError) as exc:
                    broken.append(f"{owner}.{name} -> {t}: {exc}")
    finally:
        sys.path.remove(str(ROOT))
    assert not broken, broken
    assert tables > 30                  # the tables were read, not skipped


def test_bonesim_names_metrics_only_from_the_cli_and_the_bench():
    wrong = [f"{imp} -> {t}" for imp, ts in _listed()["string-imports"].items() for t in ts
             if imp.startswith("bonesim") and t.startswith("metrics")
             and not imp.startswith(("bonesim.cli.", "bonesim.bench."))]
    assert not wrong, wrong


# --- private names stay private ---------------------------------------------


def private_imports(source: str) -> set[str]:
    """Private (single underscore) names ``source`` takes from bonesim or
    metrics modules: ``from x import _y`` and ``module._y`` of a module it
    imported (``import a as _b`` imports a public name under a private alias
    and is fine)."""
    import ast

    tree = ast.parse(source)
    found, modules = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(("bonesim",
                                                                               "metrics")):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.add(a.name)
                modules.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            modules |= {(a.asname or a.name).split(".")[0] for a in node.names
                        if a.name.startswith(("bonesim", "metrics"))}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
                and node.value.id in modules and node.value.id not in ("self", "cls")):
            found.add(node.attr)
    return found


def test_private_import_scan_finds_planted_ones():
    src = ("from bonesim.engine import haptics\n"
           "from bonesim.io import anatomy as _anatomy\n"
           "from metrics.cohort import _client, find_sessions\n"
           "haptics._begin(1)\n")
    assert private_imports(src) == {"_client", "_begin"}


def test_no_module_imports_another_modules_private_names():
    wrong = {}
    for p in sorted([*(ROOT / "bonesim").rglob("*.py"), *(ROOT / "metrics").rglob("*.py")]):
        mod = ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        names = private_imports(p.read_text())
        if names:
            wrong[mod] = sorted(names)
    assert not wrong, f"private names imported from other modules: {wrong}"
