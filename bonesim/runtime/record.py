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
           "case_sha256", "burr_sha256", "model_sha256", "make_header",
           "sessions_folder", "default_session_path", "SessionWriter",
           "compact_session", "Drainer", "Recorder"]

#: Version of the file layout written here (``docs/session_schema.md``).
SCHEMA_VERSION = 2
#: Value of the root attribute ``format``.
FORMAT = "bonesim-session"
#: How often the writer drains the rings and flushes the file [s].
FLUSH_S = 0.05
#: The writer asks for this much more CPU priority (nice -10; needs the right
#: to, as the haptic loop's real-time priority does): a starved writer falls
#: behind, and a crash then loses more than one flush period.
WRITER_NICE = 10
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
class SessionWriter:
    """Appends batches of records to a new session file (SWMR mode).

    While the file grows its columns are stored raw: a live writer flushing
    small batches every :data:`FLUSH_S` would otherwise rewrite its partly
    filled compressed chunks into new space at every flush. When the writer
    closes, the file is compacted (:func:`compact_session`): rewritten
    compressed and put in place atomically, so a crash at any moment leaves
    either the raw file or the compacted one, both complete.

    Parameters
    ----------
    path : path
        New file; an existing file is an error unless ``overwrite``.
    header : dict
        See :func:`make_header`.
    overwrite : bool
    compact : bool
        Compact the file on :meth:`close`.
    """

    def __init__(self, path, header: dict, overwrite: bool = False,
                 compact: bool = True):
        h5py = _h5py()
        self.compact = compact
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise BonesimError(f"{self.path}: a file of that name exists; choose another "
                               "--record path")
        missing = [k for k in HEADER_KEYS if k not in header]
        if missing:
            raise ValueError(f"session header lacks {missing}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            f = h5py.File(self.path, "w", libver="latest")
        except OSError as exc:
            raise BonesimError(f"{self.path}: cannot create the session file ({exc})") from exc
        self.f = f
        f.attrs["format"] = FORMAT
        f.attrs["schema"] = SCHEMA_VERSION
        f.attrs["header"] = json.dumps(header)
        self.rows = {}
        for g, cols in GROUPS.items():
            grp = f.create_group(g)
            for name, (dt, shape) in cols.items():
                grp.create_dataset(name, shape=(0,) + tuple(shape),
                                   maxshape=(None,) + tuple(shape),
                                   chunks=(CHUNK_ROWS[g],) + tuple(shape), dtype=np.dtype(dt))
            self.rows[g] = 0
        # ``closed`` turns 1 when the writer finishes cleanly; attributes
        # cannot change under SWMR, datasets can
        f.create_dataset("closed", data=np.zeros(1, np.uint8))
        f.swmr_mode = True
        self.flushes = 0

    def append(self, group: str, cols: dict) -> int:
        """Append rows (``cols``: column name -> array, equal lengths); returns
        the number appended. Columns absent from ``cols`` are filled with their
        defaults (0, or -1 for ``visible``)."""
        spec = GROUPS[group]
        n = len(next(iter(cols.values()))) if cols else 0
        if n == 0:
            return 0
        grp = self.f[group]
        r0 = self.rows[group]
        for name, (dt, shape) in spec.items():
            ds = grp[name]
            ds.resize((r0 + n,) + tuple(shape))
            if name in cols:
                ds[r0:r0 + n] = np.asarray(cols[name]).astype(dt, copy=False)
            else:                  # written, so a salvage finds every row's chunk
                ds[r0:r0 + n] = -1 if name == "visible" else 0
        self.rows[group] = r0 + n
        return n

    def flush(self) -> None:
        """Make everything appended so far durable and visible to readers."""
        for g in GROUPS:
            for ds in self.f[g].values():
                ds.flush()
        self.f.flush()
        self.flushes += 1

    def close(self) -> None:
        """Mark the file complete, close it and compact it (if asked)."""
        if self.f is None:
            return
        self.flush()
        self.f["closed"][0] = 1
        self.f["closed"].flush()
        self.f.close()
        self.f = None
        if self.compact:
            compact_session(self.path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def compact_session(path) -> int:
    """Rewrite a session file with every column compressed; returns its new size.

    The copy (gzip level :data:`COMPACT_GZIP_LEVEL` with byte shuffling,
    chunks of up to :data:`COMPACT_CHUNK_ROWS` rows) is written beside the
    file, flushed to disk and then renamed over it, so the session is never
    lost or half-written. The content (attributes, every group and column,
    the ``closed`` flag) is identical.

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
    """
    h5py = _h5py()
    path = Path(path)
    tmp = path.with_name(f".{path.name}.compacting")
    try:
        with h5py.File(path, "r") as src, \
                h5py.File(tmp, "w", libver="latest", rdcc_nbytes=0) as dst:
            for k, v in src.attrs.items():
                dst.attrs[k] = v
            pieces = []                       # (start time, group, row) per chunk
            for name, item in src.items():
                if not isinstance(item, h5py.Group):
                    dst.create_dataset(name, data=item[()])
                    continue
                grp = dst.create_group(name)
                for col, ds in item.items():
                    n = ds.shape[0]
                    opts = {}
                    if n:
                        opts = {"compression": "gzip", "compression_opts": COMPACT_GZIP_LEVEL,
                                "shuffle": True,
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
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
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


def _run_writer(child, loop_handle, path, header, flush_s, overwrite, models,
                eye_mm) -> None:
    """Body of the recorder's writer process (:meth:`Recorder.run`)."""
    from bonesim.runtime.haptic_loop import attach

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
    drainer = Drainer(writer, rings, vis)
    child.ready()
    try:
        # quit (or SIGTERM: the parent died, or terminate()) ends as asked, file complete
        while not child.quit:
            t0 = time.monotonic()
            drainer.drain()
            writer.flush()
            status["rows"] = drainer.rows
            status["flushes"] = writer.flushes
            status["overflows"] = drainer.overflows
            status["last_flush"] = time.time()
            status["visible"] = drainer.visible
            status["hidden"] = drainer.hidden
            time.sleep(max(0.0, flush_s - (time.monotonic() - t0)))
        drainer.drain()
        status["rows"] = drainer.rows
        status["visible"] = drainer.visible
        status["hidden"] = drainer.hidden
    finally:
        writer.close()
        status["flushes"] = writer.flushes
        rings.clear()
        lsh.close()


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
              ("last_flush", np.float64), ("visible", np.int64), ("hidden", np.int64))
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
        """Rows written, flushes and overflows so far."""
        s = self.status
        return {"rows": int(s["rows"]), "flushes": int(s["flushes"]),
                "overflows": int(s["overflows"]), "path": str(self.path)}

    def close(self, timeout_s: float = 30.0) -> dict:
        """Drain what is left, close the file cleanly and stop the writer;
        returns :meth:`stats` (idempotent)."""
        if self._sh is None:
            return self._final
        self.stop(timeout_s)
        self._final = self.stats()
        super().close()
        return self._final
