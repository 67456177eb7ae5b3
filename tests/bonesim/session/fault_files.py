"""Small session files for the fault matrix: written by the real
:class:`~bonesim.session.writer.SessionWriter` from synthetic rows (no
engine), so hundreds of damaged copies read in seconds."""
from __future__ import annotations

import os
import shutil

import numpy as np

from bonesim.engine import events
from bonesim.session import writer
from bonesim.session.schema import GROUPS, HEADER_KEYS
from bonesim.session.writer import SessionWriter

__all__ = ["HEADER", "ROWS", "write_synthetic", "flip_bit", "cut"]

#: A header with every key a file must carry (values of the phantom's kind).
HEADER = {k: "" for k in HEADER_KEYS} | {
    "bonesim_version": "test", "case": {"name": "phantom", "path": None, "sha256": "0" * 64},
    "burrs": [{"name": "cutting-5mm", "sha256": "1" * 64, "path": None}],
    "oversample": 2, "voxel_mm": 0.5, "structures": [{"label": 1, "name": "bone",
                                                       "kind": "bone"}],
    "device": {"name": "scripted", "max_force_n": 8.0, "workspace_mm": [None, None, None],
               "max_stiffness_n_per_mm": None, "rate_hz": 1000.0},
    "rate_hz": 1000.0, "start_time": "2026-01-01T00:00:00+00:00",
    "model_sha256": ["2" * 64], "machine": {}}
#: Rows per group of a synthetic file (samples span several live chunks).
ROWS = {"samples": 9000, "tissue": 3000, "camera": 500, "events": 10}


def _rows(group: str, n: int, rng) -> dict:
    cols = {}
    for name, (dt, shape) in GROUPS[group].items():
        dt = np.dtype(dt)
        if name == "t_s":
            cols[name] = np.arange(n) * (1e-3 if group == "samples" else 3e-3)
        elif dt.kind == "f":
            cols[name] = rng.normal(size=(n,) + tuple(shape)).astype(dt)
        elif dt.kind == "S":
            cols[name] = np.array([b"x%d" % (i % 7) for i in range(n)], dt)
        else:
            cols[name] = rng.integers(0, 3, size=(n,) + tuple(shape)).astype(dt)
    if group == "tissue":
        cols["kind"] = np.full(n, events.REMOVED, cols["kind"].dtype)
    return cols


def write_synthetic(path, compact: bool, seed: int = 0, chunk_rows: int | None = None):
    """Write a closed synthetic session (compacted or left raw); returns the
    rows written per group."""
    rng = np.random.default_rng(seed)
    data = {g: _rows(g, n, rng) for g, n in ROWS.items()}
    old = writer.COMPACT_CHUNK_ROWS
    if chunk_rows is not None:
        writer.COMPACT_CHUNK_ROWS = chunk_rows
    try:
        with SessionWriter(path, HEADER, compact=compact) as w:
            for q in range(3):                     # a few flushes, as a live writer does
                for g, cols in data.items():
                    n = len(cols["t_s"])
                    a, b = q * n // 3, (q + 1) * n // 3
                    w.append(g, {k: v[a:b] for k, v in cols.items()})
                w.flush()
    finally:
        writer.COMPACT_CHUNK_ROWS = old
    return data


def flip_bit(src, dst, offset: int, bit: int = 0):
    """Copy ``src`` to ``dst`` with one bit flipped at byte ``offset``."""
    shutil.copy(src, dst)
    with open(dst, "r+b") as f:
        f.seek(offset)
        b = f.read(1)[0]
        f.seek(offset)
        f.write(bytes([b ^ (1 << bit)]))
    return dst


def cut(src, dst, size: int):
    """Copy ``src`` to ``dst`` cut to ``size`` bytes."""
    shutil.copy(src, dst)
    os.truncate(dst, size)
    return dst
