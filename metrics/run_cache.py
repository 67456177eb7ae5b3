"""A cache of the per-run part of a cohort's scoring (``metrics cohort``/``progress``).

Scoring a run (:func:`metrics.cohort.score_file`: visibility, the force
table, conduct, the drilled set ...) is the slow part of a cohort and depends
only on the run's file and a few settings, so a second ``bonesim metrics
progress`` on an unchanged cohort reads each run's result back instead of
scoring it again.

Key
    The SHA-256 of the run file's bytes, the bonesim version, a fingerprint
    of the scoring code (the SHA-256 of every ``.py`` and ``.toml`` file of
    the ``bonesim`` and ``metrics`` packages, so an edited metric is never
    read from an older cache) and the settings (structure, ``close_mm``, row
    providers, the cohort's case). A changed file, version, code or setting
    is a different key: the run is scored again.
Entries
    One pickle per key (protocol 5) in the cache folder, written to a
    temporary name and renamed, so a reader never sees half an entry. Only
    clean results are kept: a run that failed, was salvaged from damage or
    gave warnings is scored again each time (its messages name its path).
    An entry that cannot be read is a miss (and is rewritten).

The default folder is ``$XDG_CACHE_HOME/bonesim/runs`` (``~/.cache/...``).
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
from functools import lru_cache
from pathlib import Path

from metrics.provenance import sha256_of

__all__ = ["default_cache_dir", "code_fingerprint", "RunCache"]


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/bonesim/runs``, or ``~/.cache/bonesim/runs``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "bonesim" / "runs"


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """SHA-256 over the relative paths and bytes of every ``.py`` and
    ``.toml`` file of the ``bonesim`` and ``metrics`` packages (hex)."""
    import bonesim
    import metrics

    h = hashlib.sha256()
    for pkg in (bonesim, metrics):
        root = Path(pkg.__file__).parent
        for p in sorted(x for x in root.rglob("*") if x.suffix in (".py", ".toml")):
            h.update(str(p.relative_to(root.parent)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
            h.update(b"\0")
    return h.hexdigest()


class RunCache:
    """Per-run scoring results on disk (module notes).

    Parameters
    ----------
    folder : path
        Created if missing.
    settings : dict
        JSON-able settings the result depends on (part of every key).

    Attributes
    ----------
    hits, misses, stored : int
        Counts since construction.
    """

    def __init__(self, folder, settings: dict):
        from bonesim import __version__

        self.folder = Path(folder)
        # entries are pickles: the folder is the user's own (mode 0700), like
        # any cache whose entries are loaded back
        self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._salt = json.dumps({"bonesim": __version__, "code": code_fingerprint(),
                                 "settings": settings}, sort_keys=True, default=str)
        self.hits = self.misses = self.stored = 0
        self._keys: dict = {}

    def key(self, path) -> str:
        """The entry name of ``path`` as it is now (its bytes hashed once per
        cache object)."""
        p = str(path)
        if p not in self._keys:
            h = hashlib.sha256(self._salt.encode())
            h.update(sha256_of(p).encode())
            self._keys[p] = h.hexdigest()
        return self._keys[p]

    def get(self, path) -> dict | None:
        """The cached result of ``path`` (its ``file`` set to ``path``), or None."""
        f = self.folder / f"{self.key(path)}.pkl"
        try:
            with open(f, "rb") as fh:
                r = pickle.load(fh)
            if not isinstance(r, dict) or "metrics" not in r:
                raise ValueError("not a run result")
        except FileNotFoundError:
            self.misses += 1
            return None
        except Exception:                   # unreadable entry: a miss, rewritten later
            self.misses += 1
            return None
        self.hits += 1
        return {**r, "file": str(path)}

    def put(self, path, result: dict) -> bool:
        """Keep ``result`` if it is clean (module notes); returns whether it was."""
        if "error" in result or result.get("damage") or result.get("warnings"):
            return False
        f = self.folder / f"{self.key(path)}.pkl"
        tmp = f.with_name(f"{f.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as fh:
                pickle.dump(result, fh, protocol=5)
            tmp.replace(f)
        except OSError:                     # a full or read-only cache: just not kept
            tmp.unlink(missing_ok=True)
            return False
        self.stored += 1
        return True
