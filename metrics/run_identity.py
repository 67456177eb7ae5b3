"""Telling the runs of a cohort apart: a copied recording counts once.

A cohort folder may hold the same recorded run twice: a byte-identical copy
(``cp a.h5 b.h5``) or a partial copy (a file cut short while copied, whose
readable part is the run's start). Scored as two participants' runs, such a
copy turns group differences "significant" that are not. :func:`distinct_runs`
finds them before anything is scored:

* the **content hash** (SHA-256 of the file's bytes) tells byte-identical
  copies;
* the **run hash** (SHA-256 of the header the recorder wrote: case, burrs,
  participant, start time, machine, model hash, ...; canonical JSON) tells
  copies of the same run that differ in length: every recording of one run
  carries the same header. A file whose header cannot be read falls back to
  its content hash.

Of each group of copies the largest file is kept (the most of the run;
ties: the first by name); each other one is reported in one line and left
out.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

__all__ = ["content_hash", "run_hash", "distinct_runs"]

_CHUNK = 1 << 20


def content_hash(path) -> str:
    """SHA-256 of a file's bytes (hex), read 1 MiB at a time."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def run_hash(path) -> str | None:
    """SHA-256 (hex) of the run's header as canonical JSON, or None if the
    file's header cannot be read (salvaged files are read too)."""
    try:
        import h5py

        from bonesim.session.salvage import open_session_file

        f, _, _, view = open_session_file(Path(path), h5py)
        try:
            with f:
                header = json.loads(f.attrs["header"])
        finally:
            if view is not None:
                view.close()
    except Exception:                        # unreadable: scored (and reported) as it is
        return None
    text = json.dumps(header, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def distinct_runs(paths) -> tuple[list, list, dict]:
    """The cohort's files with every copy of a run left out.

    Parameters
    ----------
    paths : sequence of Path
        The session files, in the cohort's order.

    Returns
    -------
    kept : list of Path
        One file per run, in the order given.
    notices : list of str
        One line per file left out: which file it repeats and how
        (byte-identical, or the same run's header in a smaller file).
    copies : dict of str -> str
        Left-out file -> the kept file it repeats.
    """
    info = []
    for p in map(Path, paths):
        try:
            size = p.stat().st_size
            digest = content_hash(p)
        except OSError:                      # unreadable: the scoring reports it
            info.append((p, None, None, -1))
            continue
        info.append((p, digest, run_hash(p) or digest, size))
    best: dict = {}
    for p, digest, run, size in info:
        if run is None:
            continue
        held = best.get(run)
        if held is None or size > held[3]:
            best[run] = (p, digest, run, size)
    kept, notices, copies = [], [], {}
    for p, digest, run, size in info:
        keep = best.get(run)
        if run is None or keep[0] == p:
            kept.append(p)
            continue
        how = ("a byte-identical copy" if digest == keep[1] else
               f"a copy of the same run ({size} of {keep[3]} bytes: same header)")
        notices.append(f"{p}: {how} of {keep[0]}; the run is counted once")
        copies[str(p)] = str(keep[0])
    return kept, notices, copies
