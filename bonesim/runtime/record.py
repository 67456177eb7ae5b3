"""Session recording: one HDF5 file per run, readable while it is written.

A recording holds everything needed to review, replay and score a run: a
header (who, what case and burrs with content hashes, device limits), the
device-sample stream at the haptic rate, forces, the tissue-event stream
(every voxel removal, contact and injury, reset, burr change, body split and
pose: :mod:`bonesim.engine.events`), the camera stream at the frame rate and user-interface events. The
layout is documented in ``docs/session_schema.md`` and versioned by
:data:`SCHEMA_VERSION`; :func:`read_session` checks it.

How the data gets there without slowing the haptic loop
-------------------------------------------------------
The loop only appends records to shared-memory rings (``samples`` and
``tissue``; the window adds ``camera`` and ``ui``). A
:class:`Recorder` runs a writer in its own process that drains the rings
every :data:`FLUSH_S` and appends the batches to the file, which is open in
HDF5's single-writer/multiple-reader (SWMR) mode: readers may open it while
it grows, and a writer killed outright (SIGKILL) leaves a file that reads
back complete up to its last flush. In-process runs (``bonesim simulate``,
:func:`bonesim.runtime.simulate.run_trajectory`) feed a :class:`Drainer` directly.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.runtime.child import ChildProcess

__all__ = ["SCHEMA_VERSION", "FORMAT", "FLUSH_S", "WRITER_NICE", "CHUNK_ROWS",
           "COMPACT_GZIP_LEVEL", "COMPACT_CHUNK_ROWS", "GROUPS", "OPTIONAL_GROUPS",
           "HEADER_KEYS",
           "case_sha256", "burr_sha256", "model_sha256", "header_sha256", "make_header",
           "sessions_folder", "default_session_path", "SessionWriter",
           "compaction_temp", "is_compaction_temp", "compact_session", "Drainer", "Recorder",
           "WHY_BYTES", "kept_line"]

#: Version of the file layout written here (``docs/session_schema.md``).
SCHEMA_VERSION = 3
#: Value of the root attribute ``format``.
FORMAT = "bonesim-session"
#: How often the writer drains the rings and flushes the file [s].
FLUSH_S = 0.05
#: The writer asks for this much more CPU priority (nice -10; needs the right
#: to, as the haptic loop's real-time priority does): a starved writer falls
#: behind, and a crash then loses more than one flush period.
WRITER_NICE = 10
#: Size of the recorder's shared field saying why recording stopped [bytes].
WHY_BYTES = 400
#: Rows per HDF5 chunk, per group, while a file is written.
CHUNK_ROWS = {"samples": 4096, "tissue": 8192, "camera": 1024, "events": 256}
CHUNK_ROWS["handle"] = 1024
#: A closed session is rewritten compressed (:func:`compact_session`): gzip
#: at this level with byte shuffling (level 4 comes within 5% of level 9's
#: size in half its time; a 3-minute run shrinks about 9x) ...
COMPACT_GZIP_LEVEL = 4
#: ... in chunks of at most this many rows (8 s of samples at 1 kHz: a copy
#: cut short keeps the run up to the last whole chunk), copied a chunk at a time.
COMPACT_CHUNK_ROWS = 1 << 13
#: Columns of each group: name -> (dtype, trailing shape). ``samples``,
#: ``camera`` and ``events`` are the rings of the same names
#: (:data:`bonesim.engine.events.OTHER_RINGS`); ``tissue`` is the tissue-event
#: record (:data:`bonesim.engine.events.TISSUE_FIELDS`) plus ``visible`` (removals:
#: 1 visible from the eye, 0 hidden, -1 unknown; -1 for other kinds).
GROUPS = {
    "samples": events.OTHER_RINGS["samples"][1],
    "tissue": {**events.TISSUE_FIELDS, "visible": (np.int8, ())},
    "camera": events.OTHER_RINGS["camera"][1],
    "events": events.OTHER_RINGS["ui"][1],
}
#: Optional groups (a file may lack them; :func:`read_session` then gives
#: them no rows): ``handle``, an instrumented handle's readings
#: (:mod:`bonesim.runtime.handle_stream`).
GROUPS["handle"] = events.OTHER_RINGS["handle"][1]
OPTIONAL_GROUPS = ("handle",)
#: Header keys every file must carry.
HEADER_KEYS = ("bonesim_version", "case", "burrs", "oversample", "voxel_mm", "structures",
               "device", "rate_hz", "start_time", "participant", "group", "notes",
               "model_sha256", "machine")


def _h5py():
    try:
        import h5py
    except ImportError as exc:                                  # pragma: no cover
        raise BonesimError("session files need h5py (pip install h5py)") from exc
    return h5py


# ---------------------------------------------------------------------------
# Identities and the header
# ---------------------------------------------------------------------------
def _hash_path(h, path: Path) -> None:
    if path.is_dir():
        for p in sorted(q for q in path.rglob("*") if q.is_file()):
            h.update(str(p.relative_to(path)).encode())
            h.update(p.read_bytes())
    elif path.is_file():
        h.update(path.read_bytes())


def case_sha256(case) -> str:
    """Content hash of a case: its manifest and the volume files it names."""
    h = hashlib.sha256()
    h.update(Path(case.manifest).read_bytes())
    for p in (case.volume.path, case.volume.labels):
        if p is not None:
            _hash_path(h, Path(p))
    return h.hexdigest()


def burr_sha256(burr) -> str:
    """Content hash of a burr's resolved values (family values included)."""
    import dataclasses

    d = {k: v for k, v in dataclasses.asdict(burr).items() if k != "source"}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


def model_sha256(model) -> str:
    """Hash of every array the haptic step reads: equal hashes, equal physics."""
    h = hashlib.sha256()
    g = model.grid
    for a in (g.keys, g.vals, g.density, g.label, np.asarray(g.origin_mm, float),
              np.float64(g.spacing_mm), model.stiff, model.removal, model.injury,
              model.stencil.packed, model.params):
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _finite(x):
    return None if isinstance(x, float) and not math.isfinite(x) else x


def make_header(model, burrs=(), *, participant: str = "", group: str = "",
                notes: str = "", rate_hz: float | None = None,
                input_device: str = "", device_record: dict | None = None) -> dict:
    """The header of a session of ``model`` (burr 0) and further ``burrs``.

    Parameters
    ----------
    model : Model
        Must come from a case file (``model.case`` set) to be replayable.
    burrs : sequence of Burr
        Burrs 1, 2, ... the user may switch to.
    participant, group, notes : str
        Free text from the command line.
    rate_hz : float, optional
        Haptic rate [Hz] (default the model's).
    input_device : str
        Name of the input backend (``mouse``, ``scripted``, a haptic device).
    device_record : dict, optional
        A real device's backend, capability record, settings and calibration
        (:func:`bonesim.devices.registry.device_record`), kept as the
        header's ``device_record``.

    The header's ``device`` is ``model.device``, the limits the physics was
    built with, so that a replay rebuilds the same model.
    """
    import platform

    import numba

    from bonesim import __version__

    case = model.case
    dev = model.device
    all_burrs = [model.burr] + list(burrs)
    models = [model] + [model.with_burr(b) for b in burrs]
    head = {
        "bonesim_version": __version__,
        "case": {"name": model.name,
                 "path": str(Path(case.manifest).resolve()) if case is not None else None,
                 "sha256": case_sha256(case) if case is not None else None},
        "burrs": [{"name": b.name, "sha256": burr_sha256(b),
                   "path": str(b.source) if getattr(b, "source", None) else None}
                  for b in all_burrs],
        "model_sha256": [model_sha256(m) for m in models],
        "oversample": int(model.oversample),
        "voxel_mm": float(model.spacing_mm),
        "origin_mm": [float(x) for x in model.grid.origin_mm],
        "shape": [int(x) for x in model.grid.shape],
        "structures": [{"label": s, "name": st.name, "kind": st.kind}
                       for s, st in enumerate(model.structures, start=1)],
        "device": {"name": dev.name, "max_force_n": _finite(float(dev.max_force_n)),
                   "workspace_mm": [_finite(float(x)) for x in dev.workspace_mm],
                   "max_stiffness_n_per_mm": _finite(float(dev.max_stiffness_n_per_mm)),
                   "rate_hz": float(dev.rate_hz)},
        "input": str(input_device or dev.name),
        "rate_hz": float(model.haptic_rate_hz if rate_hz is None else rate_hz),
        "start_time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "participant": str(participant), "group": str(group), "notes": str(notes),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "numpy": np.__version__, "numba": numba.__version__},
    }
    if device_record is not None:
        head["device_record"] = json.loads(json.dumps(device_record))   # JSON-ready now
    return head


def sessions_folder() -> Path:
    """Where interactive runs record by default: ``$BONESIM_SESSIONS`` or
    ``$XDG_DATA_HOME/bonesim/sessions`` (``~/.local/share/...``)."""
    root = os.environ.get("BONESIM_SESSIONS")
    if not root:
        xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
        root = str(Path(xdg) / "bonesim" / "sessions")
    return Path(root)


def default_session_path(case: str, participant: str = "") -> Path:
    """A new file name in :func:`sessions_folder`: time, case and participant."""
    root = sessions_folder()
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    who = "".join(c if c.isalnum() or c in "-_" else "_" for c in participant) or "anon"
    return Path(root) / f"{stamp}-{case}-{who}.h5"


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------
def header_sha256(fmt: str, schema: int, header_json: str) -> str:
    """Checksum of a file's identity attributes: ``format``, ``schema`` and the
    header's JSON text, as stored (schema 3: the root attribute ``header_sha256``)."""
    h = hashlib.sha256()
    for part in (str(fmt), str(int(schema)), header_json):
        b = part.encode("utf-8", "surrogateescape")    # a flipped byte stays a byte
        h.update(len(b).to_bytes(8, "little") + b)
    return h.hexdigest()


class SessionWriter:
    """Appends batches of records to a new session file (SWMR mode).

    While the file grows its columns are stored raw, each chunk with a
    Fletcher32 checksum (a flipped bit in any chunk is found on reading): a
    live writer flushing small batches every :data:`FLUSH_S` would otherwise
    rewrite its partly filled compressed chunks into new space at every
    flush. The header carries a SHA-256 of itself (:func:`header_sha256`).
    When the writer closes, the file is compacted (:func:`compact_session`):
    rewritten compressed and put in place atomically, so a crash at any
    moment leaves either the raw file or the compacted one, both complete.

    The file is written through a :class:`~bonesim.runtime.disk_guard.GuardedFile`:
    a write that fails (a full disk, a file-size limit) never reaches HDF5;
    the writer stops, :attr:`failed` says why, and the file on disk keeps
    everything up to its last good flush (:attr:`kept`). Every
    :data:`~bonesim.runtime.disk_guard.SpaceLimits.check_every_s` the flush
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
                 compact: bool = True):
        from bonesim.runtime.disk_guard import GuardedFile, load_space_limits

        h5py = _h5py()
        self.compact = compact
        self.path = Path(path)
        self.f = None
        if self.path.exists() and not overwrite:
            raise BonesimError(f"{self.path}: a file of that name exists; choose another "
                               "--record path")
        missing = [k for k in HEADER_KEYS if k not in header]
        if missing:
            raise ValueError(f"session header lacks {missing}")
        self.limits = load_space_limits()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.guard = GuardedFile(self.path, overwrite=overwrite)
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
            from bonesim.runtime.disk_guard import describe_error

            raise BonesimError(f"{self.path}: cannot create the session file: "
                               f"{describe_error(err)}")
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
        from bonesim.runtime.disk_guard import describe_error

        if self.guard.error is not None:
            return describe_error(self.guard.error)
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
            from bonesim.runtime.disk_guard import headroom_bytes

            self._next_check = now + self.limits.check_every_s
            room = headroom_bytes(self.path)
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
    from bonesim.runtime.disk_guard import GuardedFile, describe_error

    h5py = _h5py()
    path = Path(path)
    tmp = compaction_temp(path)
    tmp.unlink(missing_ok=True)
    guard = None
    try:
        guard = GuardedFile(tmp)
        with h5py.File(path, "r") as src, \
                h5py.File(guard, "w", libver="latest", rdcc_nbytes=0) as dst:
            for k, v in src.attrs.items():
                dst.attrs[k] = v
            pieces = []                       # (start time, group, row) per chunk
            for name, item in src.items():
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
            raise BonesimError(f"{path}: compacting stopped: {describe_error(guard.error)}; "
                               "the uncompressed recording is kept as it was")
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


class Drainer:
    """Moves new ring records into a :class:`SessionWriter`.

    Removals and injuries are written once the sample of their step has been
    (the loop publishes them just before that sample): a session ends with
    its last sample, and every removal in it belongs to a recorded step.

    Parameters
    ----------
    writer : SessionWriter
    rings : dict of str -> events.Ring
        Any of ``samples``, ``tissue``, ``camera``, ``ui``.
        Cursors start at record 0: the rings must not have wrapped yet.
    visibility : bonesim.physics.visibility.VisibilityTracker, optional
        Fills the removals' ``visible`` column (else -1, unknown).

    Attributes
    ----------
    visible, hidden : int
        Removals judged visible / hidden since the last case reset (the
        running visible fraction the window shows).
    """

    #: ring name -> file group, in drain order (samples before what follows them)
    TARGET = {"samples": "samples", "camera": "camera", "tissue": "tissue", "ui": "events",
              "handle": "handle"}
    #: rings held back until the samples of their steps are in
    HELD = ("tissue", "handle")

    def __init__(self, writer: SessionWriter, rings: dict, visibility=None):
        self.writer = writer
        self.cursors = {name: events.Cursor(rings[name], 0)
                        for name in self.TARGET if name in rings}
        self.visibility = visibility
        self.held = {name: None for name in self.HELD}
        self.last_t = -math.inf if "samples" in rings else math.inf
        self.rows = 0
        self.overflows = 0
        self.visible = self.hidden = 0

    def _count(self, kind, vis) -> None:
        """Add a batch's verdicts to the running counts (from 0 after a reset)."""
        resets = np.flatnonzero(kind == events.RESET)
        if len(resets):
            self.visible = self.hidden = 0
            vis = vis[resets[-1] + 1:]
        self.visible += int(np.count_nonzero(vis == 1))
        self.hidden += int(np.count_nonzero(vis == 0))

    def _take(self, name: str, cur) -> dict:
        try:
            return cur.drain()
        except events.RingOverflow:
            # the writer fell a whole ring behind (the machine stalled for a
            # minute): say so in the file and go on from what is left
            self.overflows += 1
            cur.pos = cur.ring.count - cur.ring.capacity + 1
            self.writer.append("events", {"t_s": [math.nan], "name": [b"overflow"],
                                          "value": [name.encode()]})
            return cur.drain()

    def drain(self) -> int:
        """Append everything new; returns the rows written."""
        recs = {name: self._take(name, cur) for name, cur in self.cursors.items()}
        s = recs.get("samples")
        if s is not None and len(s["t_s"]):
            self.last_t = float(s["t_s"][-1])
        for name in self.HELD:
            if name not in recs:
                continue
            r = recs[name]
            if self.held[name] is not None:
                r = {k: np.concatenate([self.held[name][k], v]) for k, v in r.items()}
            ready = r["t_s"] <= self.last_t
            self.held[name] = {k: v[~ready] for k, v in r.items()}
            recs[name] = {k: v[ready] for k, v in r.items()}
        if self.visibility is not None:
            if s is not None:
                self.visibility.add_samples(s)
            if "camera" in recs:
                self.visibility.add_camera(recs["camera"])
        if "tissue" in recs:
            r = recs["tissue"]
            r["visible"] = np.full(len(r["t_s"]), -1, np.int8) if self.visibility is None \
                else self.visibility.judge(r)
            self._count(np.asarray(r["kind"]), r["visible"])
        n = sum(self.writer.append(self.TARGET[name], r) for name, r in recs.items())
        self.rows += n
        return n


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


def _set_kept(status, kept: dict) -> None:
    status["kept_samples"] = kept["samples"]
    status["kept_removals"] = kept["removals"]
    status["kept_t0_s"] = math.nan if kept["t0_s"] is None else kept["t0_s"]
    status["kept_t_s"] = math.nan if kept["t_s"] is None else kept["t_s"]


def _fsize_hook() -> bool:
    """Test hook: ``BONESIM_TEST_WRITER_FSIZE`` [bytes] limits the size of
    files the writer process may write (``RLIMIT_FSIZE``; Python ignores
    SIGXFSZ, so a write past it fails with EFBIG, as on a full disk), and
    the writer then keeps no space back, so that the write itself fails.
    Returns True when the hook is set."""
    limit = os.environ.get("BONESIM_TEST_WRITER_FSIZE")
    if not limit:
        return False
    import resource
    import signal

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(limit), hard))
    return True


def _run_writer(child, loop_handle, path, header, flush_s, overwrite, models,
                eye_mm) -> None:
    """Body of the recorder's writer process (:meth:`Recorder.run`).

    A write that fails (or the space running out) stops the recording: the
    status's ``stopped`` and ``why`` say so, ``kept_*`` what the file holds,
    and the process ends; the parent (:meth:`Recorder.check`) tells the user.
    """
    from bonesim.runtime.haptic_loop import attach

    full_disk_test = _fsize_hook()
    lsh, rings = attach(loop_handle)
    status = child.status
    try:
        os.nice(-WRITER_NICE)    # ahead of the window and the tests' load; best effort
    except (OSError, AttributeError):
        pass
    rings = {"samples": rings["samples"], "tissue": rings["tissue"],
             "camera": child.rings["camera"], "ui": child.rings["ui"],
             **({"handle": rings["handle"]} if "handle" in rings else {})}
    vis = None
    if models is not None:
        from bonesim.physics.visibility import VisibilityTracker

        model, burrs = models
        vis = VisibilityTracker([model] + [model.with_burr(b) for b in burrs], eye_mm)
        vis.warm()                     # before ready, not at the first removal
    try:
        writer = SessionWriter(path, header, overwrite=overwrite)
    except BaseException:
        rings.clear()
        lsh.close()
        raise
    if full_disk_test:
        import dataclasses

        writer.limits = dataclasses.replace(writer.limits, reserve_mb=0.0)
    drainer = Drainer(writer, rings, vis)
    status["kept_t0_s"] = status["kept_t_s"] = math.nan
    child.ready()
    try:
        # quit (or SIGTERM: the parent died, or terminate()) ends as asked, file complete
        while not child.quit and writer.failed is None:
            t0 = time.monotonic()
            drainer.drain()
            writer.flush()
            _set_kept(status, writer.kept)
            status["rows"] = drainer.rows
            status["flushes"] = writer.flushes
            status["overflows"] = drainer.overflows
            status["last_flush"] = time.time()
            status["visible"] = drainer.visible
            status["hidden"] = drainer.hidden
            time.sleep(max(0.0, flush_s - (time.monotonic() - t0)))
        if writer.failed is None:
            drainer.drain()
            status["rows"] = drainer.rows
            status["visible"] = drainer.visible
            status["hidden"] = drainer.hidden
    finally:
        writer.close()
        _set_kept(status, writer.kept)
        status["flushes"] = writer.flushes
        status["compacted"] = int(writer.failed is None and writer.compact_error is None)
        if writer.compact_error is not None:
            status["why"] = _encode_why(writer.compact_error)
        if writer.failed is not None:
            status["why"] = _encode_why(writer.failed)
            status["stopped"] = 1
        status["closed_ok"] = 1
        rings.clear()
        lsh.close()


def _encode_why(text: str) -> bytes:
    raw = text.encode("utf-8", errors="replace")[:WHY_BYTES]
    return raw.decode("utf-8", errors="ignore").encode()


class Recorder(ChildProcess):
    """Records a running :class:`~bonesim.runtime.haptic_loop.HapticLoop` to a file.

    The writer runs in its own process (:mod:`bonesim.runtime.child`). The window
    side may add the camera pose (:meth:`camera`) and UI events
    (:meth:`event`); both are stamped with the loop's clock.

    Parameters
    ----------
    loop : HapticLoop
        Started (or about to start) within the last minute: the writer reads
        its rings from record 0.
    path : path
        New session file.
    header : dict
        See :func:`make_header`.
    flush_s : float
        Drain-and-flush period [s]; at most this much is lost to a crash.
    visibility : bool
        Judge each removal's visibility from the eye
        (:mod:`bonesim.physics.visibility`) in the writer: from the camera poses
        logged with :meth:`camera`, else from the case camera.

    Attributes
    ----------
    status : ndarray
        ``rows`` written, ``flushes``, ring ``overflows``, ``last_flush``
        (wall clock [s]); ``visible`` and ``hidden``: removals judged since
        the last case reset (:class:`Drainer`).
    """

    NAME = "bonesim-recorder"
    STATUS = (("rows", np.int64), ("flushes", np.int64), ("overflows", np.int64),
              ("last_flush", np.float64), ("visible", np.int64), ("hidden", np.int64),
              ("kept_t0_s", np.float64), ("kept_t_s", np.float64),
              ("kept_samples", np.int64), ("kept_removals", np.int64),
              ("stopped", np.uint8), ("closed_ok", np.uint8), ("compacted", np.uint8),
              ("why", f"S{WHY_BYTES}"))
    RINGS = ("camera", "ui")
    TERM_QUITS = True               # SIGTERM: drain the rings and close the file

    def __init__(self, loop, path, header: dict, flush_s: float = FLUSH_S,
                 overwrite: bool = False, visibility: bool = True):
        self.loop = loop
        self.path = Path(path)
        super().__init__()
        self._camera = self.rings["camera"]
        self._ui = self.rings["ui"]
        cam = getattr(getattr(loop.model, "case", None), "camera", None)
        judge = visibility and cam is not None
        self._args = {"loop_handle": loop.handle, "path": str(self.path), "header": header,
                      "flush_s": flush_s, "overwrite": overwrite,
                      "models": ((loop.model, [b for b in loop.burrs[1:]]) if judge
                                 else None),
                      "eye_mm": np.asarray(cam.eye_mm, float) if judge else None}

    def child_args(self) -> dict:
        return self._args

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_writer(child, **kwargs)

    def _now(self) -> float:
        return float(self.loop.status["t_s"])

    def camera(self, eye_mm, focal_mm, up) -> None:
        """Log the camera pose (call once per frame)."""
        r = self._camera
        q = r.count & (r.capacity - 1)
        r.fields["t_s"][q] = self._now()
        r.fields["eye_mm"][q] = eye_mm
        r.fields["focal_mm"][q] = focal_mm
        r.fields["up"][q] = up
        r.head[0] += 1

    def event(self, name: str, value="") -> None:
        """Log a user-interface event (key, burr change, reset, ...)."""
        r = self._ui
        q = r.count & (r.capacity - 1)
        r.fields["t_s"][q] = self._now()
        r.fields["name"][q] = str(name).encode()[:16]
        r.fields["value"][q] = str(value).encode()[:64]
        r.head[0] += 1

    def stats(self) -> dict:
        """Rows written, flushes and overflows so far, and the recording's
        state: ``record_ok`` (False once it stopped early or the writer
        died), ``record_kept`` (``t0_s``, ``t_s``, ``samples``,
        ``removals``: what the file holds for sure) and ``record_error``
        (one line, or None)."""
        s = self.status
        t0, t1 = float(s["kept_t0_s"]), float(s["kept_t_s"])
        return {"rows": int(s["rows"]), "flushes": int(s["flushes"]),
                "overflows": int(s["overflows"]), "path": str(self.path),
                "record_ok": self.failure is None,
                "record_kept": {"t0_s": None if math.isnan(t0) else round(t0, 4),
                                "t_s": None if math.isnan(t1) else round(t1, 4),
                                "samples": int(s["kept_samples"]),
                                "removals": int(s["kept_removals"])},
                "record_error": self.failure}

    @property
    def failure(self) -> str | None:
        """One line once the recording has stopped early (see :meth:`check`)."""
        return getattr(self, "_failure", None)

    def check(self) -> str | None:
        """Look at the writer (cheap: call it every frame). Returns one line
        the first time the recording is found stopped (a write failed, the
        disk filled, the writer process died), else None; the line stays in
        :attr:`failure`."""
        if self.failure is not None or self._sh is None:
            return None
        s = self.status
        why = None
        if s["stopped"]:
            why = bytes(s["why"].item()).decode("utf-8", errors="replace")
        elif not self.running and not self.control["quit"] and self._proc is not None:
            code = self._proc.exitcode
            how = (f"killed by signal {-code}" if code is not None and code < 0
                   else f"exit code {code}")
            why = f"the recorder process died ({how})"
        if why is None:
            return None
        self._failure = kept_line(self.path, why, self.stats()["record_kept"])
        return self._failure

    def close(self, timeout_s: float = 30.0) -> dict:
        """Drain what is left, close the file cleanly and stop the writer;
        returns :meth:`stats` (idempotent). A writer that did not finish
        closing the file (it died, or stopped early) shows in
        ``record_ok``; a compaction that failed (the raw file is kept,
        complete) in ``compact_error``."""
        if self._sh is None:
            return self._final
        self.check()
        self.stop(timeout_s)
        if self.failure is None and not self.status["closed_ok"]:
            code = None if self._proc is None else self._proc.exitcode
            self._failure = kept_line(self.path, "the recorder process ended without closing "
                                      "the file" + (f" (exit code {code})" if code else ""),
                                      self.stats()["record_kept"])
        self.check()
        self._final = self.stats()
        if self.status["closed_ok"] and not self.status["compacted"] and self.failure is None:
            self._final["compact_error"] = bytes(self.status["why"].item()).decode(
                "utf-8", errors="replace")
        super().close()
        return self._final
