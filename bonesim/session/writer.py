"""Writing a session file: :class:`SessionWriter` appends rows to a new file
(readable while it grows), :func:`compact_session` rewrites a closed one
compressed, :func:`kept_line` says what a file cut short keeps.

The layout is :mod:`bonesim.session.schema`'s; the header is
:func:`bonesim.session.header.make_header`'s. The recorder process that
feeds a writer from the haptic loop's rings is
:mod:`bonesim.runtime.record`.
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.io.embedded import MODEL_GROUP, write_volume
from bonesim.session import disk_guard
from bonesim.session.header import header_sha256
from bonesim.session.schema import FORMAT, GROUPS, HEADER_KEYS, SCHEMA_VERSION, require_h5py

__all__ = ["CHUNK_ROWS", "COMPACT_GZIP_LEVEL", "COMPACT_CHUNK_ROWS", "SessionWriter",
           "compaction_temp", "is_compaction_temp", "compact_session", "kept_line"]

#: Rows per HDF5 chunk, per group, while a file is written.
CHUNK_ROWS = {"samples": 4096, "tissue": 8192, "camera": 1024, "events": 256}
CHUNK_ROWS["handle"] = 1024
#: A closed session is rewritten compressed (:func:`compact_session`): gzip at
#: this level with byte shuffling (level 4 comes within 5% of level 9's
#: size in half its time; a 3-minute run shrinks about 9x) ...
COMPACT_GZIP_LEVEL = 4
#: ... in chunks of at most this many rows (8 s of samples at 1 kHz: a copy
#: cut short keeps the run up to the last whole chunk), copied a chunk at a time.
COMPACT_CHUNK_ROWS = 1 << 13


class SessionWriter:
    """Appends batches of records to a new session file (SWMR mode).

    While the file grows its columns are stored raw, each chunk with a
    Fletcher32 checksum (a flipped bit in any chunk is found on reading): a
    live writer flushing small batches (every
    :data:`bonesim.runtime.record.FLUSH_S`) would otherwise rewrite its partly
    filled compressed chunks into new space at every flush. The header
    carries a SHA-256 of itself (:func:`header_sha256`).
    When the writer closes, the file is compacted (:func:`compact_session`):
    rewritten compressed and put in place atomically, so a crash at any
    moment leaves either the raw file or the compacted one, both complete.

    The file is written through a :class:`~bonesim.session.disk_guard.GuardedFile`:
    a write that fails (a full disk, a file-size limit) never reaches HDF5;
    the writer stops, :attr:`failed` says why, and the file on disk keeps
    everything up to its last good flush (:attr:`kept`). Every
    :data:`~bonesim.session.disk_guard.SpaceLimits.check_every_s` the flush
    also checks the space left and stops recording cleanly (the file closed,
    complete up to then, a ``stopped`` event saying why) before it runs out.

    Parameters
    ----------
    path : path
        New file; an existing file is an error unless ``overwrite``.
    header : dict
        See :func:`make_header`.
    overwrite : bool
    compact : bool
        Compact the file on :meth:`close`.
    volume : CaseVolume, optional
        The initial tissue of the recorded case
        (:func:`bonesim.session.header.recorded_volume`), stored in the group
        ``/model`` (:func:`bonesim.io.embedded.write_volume`) so that the file,
        with its header's ``model`` record, rebuilds the model on its own.

    Attributes
    ----------
    failed : str or None
        Why recording stopped early (None: it did not).
    kept : dict
        What the file holds for sure: ``t0_s`` and ``t_s`` (the first and
        last samples' times [s], None before the first), ``samples`` and
        ``removals`` (rows), as of the last good flush.
    compact_error : str or None
        Why compaction failed (the raw file is then kept, complete).
    """

    def __init__(self, path, header: dict, overwrite: bool = False,
                 compact: bool = True, volume=None):
        h5py = require_h5py()
        self.compact = compact
        self.path = Path(path)
        self.f = None
        if self.path.exists() and not overwrite:
            raise BonesimError(f"{self.path}: a file of that name exists; choose another "
                               "--record path")
        missing = [k for k in HEADER_KEYS if k not in header]
        if missing:
            raise ValueError(f"session header lacks {missing}")
        self.limits = disk_guard.load_space_limits()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.guard = disk_guard.GuardedFile(self.path, overwrite=overwrite)
        except OSError as exc:
            raise BonesimError(f"{self.path}: cannot create the session file ({exc})") from exc
        self.failed = None
        self.compact_error = None
        self.kept = {"t0_s": None, "t_s": None, "samples": 0, "removals": 0}
        self._pending = dict(self.kept)
        self._next_check = 0.0
        self._stopping = None
        try:
            f = h5py.File(self.guard, "w", libver="latest")
            self.f = f
            text = json.dumps(header)
            f.attrs["format"] = FORMAT
            f.attrs["schema"] = SCHEMA_VERSION
            f.attrs["header"] = text
            f.attrs["header_sha256"] = header_sha256(FORMAT, SCHEMA_VERSION, text)
            if volume is not None:
                write_volume(f, volume, header["case"]["name"])
            self.rows = {}
            for g, cols in GROUPS.items():
                grp = f.create_group(g)
                for name, (dt, shape) in cols.items():
                    grp.create_dataset(name, shape=(0,) + tuple(shape),
                                       maxshape=(None,) + tuple(shape),
                                       chunks=(CHUNK_ROWS[g],) + tuple(shape),
                                       dtype=np.dtype(dt), fletcher32=True)
                self.rows[g] = 0
            # ``closed`` turns 1 when the writer finishes cleanly; attributes
            # cannot change under SWMR, datasets can
            f.create_dataset("closed", data=np.zeros(1, np.uint8), chunks=(1,), fletcher32=True)
            f.swmr_mode = True
            f.flush()
        except (OSError, RuntimeError, ValueError) as exc:
            self._abandon()
            raise BonesimError(f"{self.path}: cannot create the session file ({exc})") \
                from None
        if self.guard.error is not None:
            err = self.guard.error
            self._abandon()
            self.path.unlink(missing_ok=True)
            raise BonesimError(f"{self.path}: cannot create the session file: "
                               f"{disk_guard.describe_error(err)}")
        self.flushes = 0

    def _abandon(self) -> None:
        """Close the HDF5 file and the guard, whatever state they are in."""
        f, self.f = self.f, None
        if f is not None:
            try:
                f.close()
            except (OSError, RuntimeError, ValueError):
                pass
        try:
            self.guard.close()
        except OSError:
            pass

    def _fail(self, why: str) -> None:
        if self.failed is None:
            self.failed = why

    def append(self, group: str, cols: dict) -> int:
        """Append rows (``cols``: column name -> array, equal lengths); returns
        the number appended (0 once recording has stopped, :attr:`failed`).
        Columns absent from ``cols`` are filled with their defaults (0, or -1
        for ``visible``)."""
        spec = GROUPS[group]
        n = len(next(iter(cols.values()))) if cols else 0
        if n == 0 or self.failed is not None or self.f is None:
            return 0
        grp = self.f[group]
        r0 = self.rows[group]
        try:
            for name, (dt, shape) in spec.items():
                ds = grp[name]
                ds.resize((r0 + n,) + tuple(shape))
                if name in cols:
                    ds[r0:r0 + n] = np.asarray(cols[name]).astype(dt, copy=False)
                else:              # written, so a salvage finds every row's chunk
                    ds[r0:r0 + n] = -1 if name == "visible" else 0
        except (OSError, RuntimeError, ValueError) as exc:
            self._fail(self._why(exc))
            return 0
        self.rows[group] = r0 + n
        if group == "samples" and "t_s" in cols:
            t = np.asarray(cols["t_s"])
            if self._pending["t0_s"] is None:
                self._pending["t0_s"] = float(t[0])
            self._pending["t_s"] = float(t[-1])
            self._pending["samples"] = self.rows[group]
        elif group == "tissue" and "kind" in cols:
            self._pending["removals"] += int(np.count_nonzero(
                np.asarray(cols["kind"]) == events.REMOVED))
        return n

    def _why(self, exc=None) -> str:
        if self.guard.error is not None:
            return disk_guard.describe_error(self.guard.error)
        return f"a write failed ({str(exc).splitlines()[0] if exc else '?'})"

    def flush(self) -> None:
        """Make everything appended so far durable and visible to readers;
        checks the space left now and then (see the class notes)."""
        if self.failed is not None or self.f is None:
            return
        try:
            for g in GROUPS:
                for ds in self.f[g].values():
                    ds.flush()
            self.f.flush()
        except (OSError, RuntimeError, ValueError) as exc:
            self._fail(self._why(exc))
            return
        if self.guard.error is not None:
            self._fail(self._why())
            return
        self.kept = dict(self._pending)
        self.flushes += 1
        now = time.monotonic()
        if now >= self._next_check and self._stopping is None:
            self._next_check = now + self.limits.check_every_s
            room = disk_guard.headroom_bytes(self.path)
            if room < self.limits.reserve_mb * (1 << 20):
                self.stop(f"the disk is nearly full ({room / (1 << 20):.1f} MB left)")

    def stop(self, why: str) -> None:
        """Stop recording now, cleanly: a ``stopped`` event says why, the file
        is closed complete up to here (:attr:`failed` is ``why``)."""
        if self.failed is not None or self.f is None or self._stopping is not None:
            return
        self._stopping = why
        self.append("events", {"t_s": [math.nan], "name": [b"stopped"],
                               "value": [why.encode()[:64]]})
        self.close()

    def close(self) -> None:
        """Mark the file complete, close it and compact it (if asked). After a
        failed write the file is left as the failure found it (readable up to
        :attr:`kept`) and not compacted."""
        if self.f is None:
            return
        stopping = self._stopping
        if self.failed is None:
            self.flush()
        if self.failed is None:
            try:
                self.f["closed"][0] = 1
                self.f["closed"].flush()
                self.f.close()
                self.f = None
                self.guard.sync()
            except (OSError, RuntimeError, ValueError) as exc:
                self._fail(self._why(exc))
            if self.guard.error is not None:
                self._fail(self._why())
        self._abandon()
        if stopping is not None:
            self.failed = stopping
        elif self.failed is None and self.compact:
            try:
                compact_session(self.path)
            except BonesimError as exc:
                self.compact_error = str(exc)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def compaction_temp(path) -> Path:
    """The temporary file :func:`compact_session` writes beside ``path``."""
    path = Path(path)
    return path.with_name(f".{path.name}.compacting")


def is_compaction_temp(path) -> bool:
    """True for a file named as :func:`compaction_temp` names them."""
    name = Path(path).name
    return name.startswith(".") and name.endswith(".compacting")


def compact_session(path) -> int:
    """Rewrite a session file with every column compressed; returns its new size.

    The copy (gzip level :data:`COMPACT_GZIP_LEVEL` with byte shuffling and a
    Fletcher32 checksum per chunk, chunks of up to :data:`COMPACT_CHUNK_ROWS`
    rows) is written beside the file (:func:`compaction_temp`, a leftover of
    an earlier interrupted compaction is removed first), flushed to disk and
    then renamed over it (``os.replace``), so the session is never lost or
    half-written. The content (attributes, every group and column, the
    ``closed`` flag) is identical.

    The copy is laid out in time order: every group and column is created
    first (all metadata at the file's start), then the chunks are written
    straight to disk (no chunk cache), all columns of a group's chunk
    together, chunks ordered by the time of their first row. A copy cut
    short (a full disk, an interrupted transfer) so keeps the run's
    beginning in every stream, which :func:`bonesim.session.reader.read_session`
    salvages.

    Parameters
    ----------
    path : path
        A session file no writer holds open.

    Returns
    -------
    int
        Size of the compacted file [bytes].

    Raises
    ------
    BonesimError
        The copy could not be written (a full disk: one line saying so); the
        temporary is removed and ``path`` is left as it was.
    """
    h5py = require_h5py()
    path = Path(path)
    tmp = compaction_temp(path)
    tmp.unlink(missing_ok=True)
    guard = None
    try:
        guard = disk_guard.GuardedFile(tmp)
        with h5py.File(path, "r") as src, \
                h5py.File(guard, "w", libver="latest", rdcc_nbytes=0) as dst:
            for k, v in src.attrs.items():
                dst.attrs[k] = v
            pieces = []                       # (start time, group, row) per chunk
            for name, item in src.items():
                if name == MODEL_GROUP:       # the recorded case: compressed already
                    src.copy(item, dst, name=name)
                    continue
                if not isinstance(item, h5py.Group):
                    dst.create_dataset(name, data=item[()], fletcher32=True,
                                       chunks=item.shape or None)
                    continue
                grp = dst.create_group(name)
                for col, ds in item.items():
                    n = ds.shape[0]
                    opts = {}
                    if n:
                        opts = {"compression": "gzip", "compression_opts": COMPACT_GZIP_LEVEL,
                                "shuffle": True, "fletcher32": True,
                                "chunks": (min(n, COMPACT_CHUNK_ROWS),) + ds.shape[1:]}
                    grp.create_dataset(col, shape=ds.shape, maxshape=ds.shape,
                                       dtype=ds.dtype, **opts)
                first = next(iter(item.values()), None)
                t = item["t_s"] if "t_s" in item else None
                rows = 0 if first is None else first.shape[0]
                pieces += [(float(t[r]) if t is not None else -math.inf, name, r)
                           for r in range(0, rows, COMPACT_CHUNK_ROWS)]
            dst.flush()                       # the metadata lands at the start
            for _, name, r in sorted(pieces, key=lambda p: (p[0], list(GROUPS).index(p[1])
                                                              if p[1] in GROUPS else 99)):
                for col, ds in src[name].items():
                    dst[name][col][r:r + COMPACT_CHUNK_ROWS] = ds[r:r + COMPACT_CHUNK_ROWS]
                if guard.error is not None:
                    break                     # the disk filled: stop copying
        guard.sync()
        if guard.error is not None:
            why = disk_guard.describe_error(guard.error)
            raise BonesimError(f"{path}: compacting stopped: {why}; the uncompressed "
                               "recording is kept as it was")
        guard.close()
        os.replace(tmp, path)
    except (OSError, RuntimeError, ValueError) as exc:
        if guard is not None:
            guard.close()
        tmp.unlink(missing_ok=True)
        raise BonesimError(f"{path}: compacting failed ({str(exc).splitlines()[0]}); the "
                           "uncompressed recording is kept as it was") from None
    except BaseException:
        if guard is not None:
            guard.close()
        tmp.unlink(missing_ok=True)
        raise
    return path.stat().st_size


def kept_line(path, why: str, kept: dict) -> str:
    """One line for a recording that stopped early: why, and what the file keeps.

    Parameters
    ----------
    path : path
        The session file.
    why : str
        What stopped it.
    kept : dict
        ``t0_s``, ``t_s``, ``samples``, ``removals`` (see :attr:`SessionWriter.kept`).
    """
    if not kept.get("samples"):
        return f"recording stopped: {why}; {path} keeps no samples of the run"
    return (f"recording stopped at {kept['t_s']:.1f} s: {why}; {path} keeps the run from "
            f"{kept['t0_s']:.1f} to {kept['t_s']:.1f} s ({kept['samples']:,} samples, "
            f"{kept['removals']:,} removals); the run went on unrecorded")
