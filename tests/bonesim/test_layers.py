"""The package's layering: the import-linter contracts in pyproject.toml hold,
and no import cycle exists, imports inside functions included."""
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
        return grimp.build_graph("bonesim", include_external_packages=False,
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
