"""Where a result came from: what every research output records.

:func:`provenance` gathers, JSON-ready: the bonesim version that made the
output (and the versions that recorded the runs), the case and burrs with
their content hashes (from the session headers; several values are listed
when runs differ), the participants file's SHA-256, the synthesis seed and
parameters when the runs are a synthetic cohort (``synthesis.json`` beside
the participants table, written by :func:`metrics.synth.synth_cohort`), the
command line and the time. The exports (:mod:`metrics.exports`) and the
report carry it.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import shlex
import sys
from pathlib import Path

__all__ = ["SYNTHESIS_JSON", "sha256_of", "file_sha256", "provenance"]

#: Written beside a synthetic cohort's participants table.
SYNTHESIS_JSON = "synthesis.json"


def sha256_of(path) -> str:
    """SHA-256 of a file's bytes (hex), read in 1 MiB chunks (OSError when it
    cannot be read)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def file_sha256(path) -> str | None:
    """SHA-256 of a file's bytes (hex), or None if it cannot be read."""
    try:
        return sha256_of(path)
    except OSError:
        return None


def provenance(headers=(), participants=None, *, command: str | None = None,
               seed=None) -> dict:
    """The provenance record of an output (module docstring).

    Parameters
    ----------
    headers : sequence of dict
        Session headers (or their ``bonesim_version``, ``case`` and ``burrs``).
    participants : path, optional
        The participants table.
    command : str, optional
        The command line (default ``sys.argv``, quoted).
    seed : int, optional
        The synthesis seed, when not in ``synthesis.json``.

    Returns
    -------
    dict
        ``bonesim_version``, ``recorded_with`` (versions), ``case`` (name,
        sha256: one entry per distinct case), ``burrs`` (name, sha256),
        ``participants_file`` and ``participants_sha256``, ``synthesis``
        (seed and parameters, or None), ``command``, ``created``.
    """
    from bonesim import __version__

    cases, burrs, versions = {}, {}, set()
    for h in headers:
        c = h.get("case") or {}
        cases[(c.get("name"), c.get("sha256"))] = None
        for b in h.get("burrs") or ():
            burrs[(b.get("name"), b.get("sha256"))] = None
        if h.get("bonesim_version"):
            versions.add(str(h["bonesim_version"]))
    synth = None
    if participants is not None:
        f = Path(participants).parent / SYNTHESIS_JSON
        if f.is_file():
            try:
                synth = json.loads(f.read_text())
            except (OSError, ValueError):
                synth = {"error": f"{f}: unreadable"}
    if synth is None and seed is not None:
        synth = {"seed": int(seed)}
    return {"bonesim_version": __version__, "recorded_with": sorted(versions),
            "case": [{"name": n, "sha256": s} for n, s in cases],
            "burrs": [{"name": n, "sha256": s} for n, s in sorted(burrs, key=str)],
            "participants_file": str(participants) if participants is not None else None,
            "participants_sha256": file_sha256(participants) if participants is not None
            else None,
            "synthesis": synth,
            "command": command if command is not None else shlex.join(sys.argv),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
