"""Reading session files: the schema check, summaries, and damaged files.

:func:`read_session` reads a file written by :mod:`bonesim.session.writer` and checks
it against the schema (``docs/session_schema.md``). It never waits on a file
that no writer holds and never ends in a raw HDF5 error: a damaged file (cut
short, zeroed blocks, left open by a writer that died; see
:mod:`bonesim.session.salvage`) is read up to where it stops being readable,
every stream cut at the same moment so that replaying its samples gives its
removals, and the :class:`Session` says what is wrong (:attr:`Session.damage`).
:func:`repair_session` writes that readable prefix as a clean file.

Files of schema 3 carry checksums: a SHA-256 of the header
(:func:`bonesim.session.header.header_sha256`) and a Fletcher32 checksum on
every chunk of every column, so a flipped bit is found and named: a header
that fails its checksum makes the session refuse to rebuild its model
(:attr:`Session.header_ok`), a chunk that fails ends that column's readable
prefix. A column whose metadata is lost loses that column only
(:attr:`Session.lost`); the other columns read.

Files of schema 1 and 2 are read too (without checksums to check): schema
1's removals, injuries, resets and burr changes are migrated into the
tissue-event stream (:mod:`bonesim.session.schema_v1`); a repaired copy is
written in the current schema.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.io.embedded import MODEL_GROUP
from bonesim.session.schema import OPTIONAL_GROUPS
from bonesim.session.schema import FORMAT, GROUPS, HEADER_KEYS, SCHEMA_VERSION, require_h5py
from bonesim.session.writer import SessionWriter, compact_session, is_compaction_temp
from bonesim.session.header import header_sha256, model_sha256, sessions_folder
from bonesim.session.salvage import open_session_file, read_prefix, read_prefix_why
from bonesim.session.schema_v1 import GROUPS_V1
from bonesim.session.schema_v1 import migrate as migrate_v1

__all__ = ["Session", "read_session", "damage_notice", "session_info", "list_sessions",
           "repair_session"]

#: Per schema: the groups read (name -> columns) and the tissue stream that
#: must be whole up to the moment a damaged file is cut at.
_SCHEMAS = {1: ({"samples": GROUPS["samples"], **GROUPS_V1, "camera": GROUPS["camera"],
                 "events": GROUPS["events"]}, "removals"),
            2: (GROUPS, "tissue"), 3: (GROUPS, "tissue"), 4: (GROUPS, "tissue")}
#: Sample columns a replay cannot do without.
REPLAY_COLUMNS = ("t_s", "pos_mm", "axis", "drill", "speed_rpm", "direction", "burr", "epoch")


@dataclass
class Session:
    """A recorded run, read into memory (see ``docs/session_schema.md``).

    Attributes
    ----------
    path : Path
    schema : int
    header : dict
    complete : bool
        The writer closed the file cleanly (False after a crash: the data is
        complete up to the writer's last flush).
    samples, tissue, camera : dict of str -> ndarray
        Columns of equal length per group. ``tissue`` is the tissue-event
        stream (:mod:`bonesim.engine.events`) with ``visible``; a schema-1 file's
        removals, injuries, resets and burr changes are migrated into it
        (:mod:`bonesim.session.schema_v1`).
    events : list of (t_s, name, value)
        User-interface events.
    damage : str or None
        What is wrong with the file (cut short, unreadable blocks, groups
        lost), in words; None for a sound file. A damaged session holds the
        file's readable prefix: every stream up to the same moment.
    readable : dict of str -> (int, int)
        Per group of a damaged file: rows kept and rows the file declares.
    repaired : dict or None
        For a copy written by :func:`repair_session`: ``from`` (the damaged
        file) and ``damage`` (what was wrong with it).
    handle : dict of str -> ndarray
        An instrumented handle's readings (``t_s``, ``angles_deg``,
        ``counts``; :mod:`bonesim.runtime.handle_stream`): no rows for runs
        without one and for files written before the group existed.
    case_version : str or None
        Set when the model was rebuilt from a kept older version of a bundled
        case (``"phantom@2"``), found by the recorded hashes.
    header_ok : bool
        False when the header fails its checksum (schema 3): its case, burrs,
        voxel size and oversampling cannot be trusted, so :meth:`burr_models`
        refuses.
    checksums : bool
        The file carries checksums (schema 3 and later).
    lost : list of str
        Columns (``/samples/force_n``) whose data could not be read at all;
        they hold NaN (floats) or 0 rows of the group's length.
    holes : list of str
        Sample columns a replay does not need (``/samples/force_n``) with
        chunks that failed their checksum: those rows read as NaN or 0 (the
        damage names them), the other columns go on.
    stopped : str or None
        Why the writer stopped recording early (its ``stopped`` event: the
        disk nearly full), else None.
    carries_model : bool
        The file holds the model it was recorded on (schema 4: the header's
        ``model`` record and the ``/model`` tissue arrays,
        :mod:`bonesim.io.embedded`): :meth:`burr_models` needs no case, burr
        or material file.
    model_source : str or None
        Set when a file carries a model that cannot be read and
        :meth:`burr_models` built it from today's case files instead (why).
    """

    path: Path
    schema: int
    header: dict
    complete: bool
    samples: dict
    tissue: dict
    camera: dict
    events: list = field(default_factory=list)
    damage: str | None = None
    readable: dict = field(default_factory=dict)
    repaired: dict | None = None
    handle: dict = field(default_factory=lambda: _no_rows(GROUPS["handle"]))
    case_version: str | None = None
    header_ok: bool = True
    checksums: bool = False
    lost: list = field(default_factory=list)
    stopped: str | None = None
    holes: list = field(default_factory=list)
    carries_model: bool = False
    model_source: str | None = None

    @cached_property
    def removals(self) -> dict:
        """The removed voxels (:func:`bonesim.engine.events.removals`) with
        ``visible`` and ``epoch`` (case resets before each removal, from the
        samples)."""
        m = self.tissue["kind"] == events.REMOVED
        rem = events.removals({k: a[m] for k, a in self.tissue.items() if k != "visible"})
        rem["visible"] = self.tissue["visible"][m]
        s = self.samples
        if len(s["t_s"]):
            idx = np.clip(np.searchsorted(s["t_s"], rem["t_s"]), 0, len(s["t_s"]) - 1)
            rem["epoch"] = s["epoch"][idx]
        else:
            rem["epoch"] = np.zeros(len(rem["t_s"]), np.int32)
        return rem

    @cached_property
    def injuries(self) -> dict:
        """Contacts and injuries (:func:`bonesim.engine.events.injuries`)."""
        return events.injuries({k: a for k, a in self.tissue.items() if k != "visible"})

    @property
    def duration_s(self) -> float:
        t = self.samples["t_s"]
        return float(t[-1] - t[0]) if len(t) else 0.0

    def burr_models(self, check: bool = True) -> list:
        """One :class:`~bonesim.engine.model.Model` per burr index, rebuilt from
        the file alone when it carries its model (:attr:`carries_model`), else
        from the recorded case and burr files (a changed bundled case: from its
        kept older versions, found by the hashes); with ``check``, their
        physics must hash to what was recorded."""
        if not self.header_ok:
            raise BonesimError(f"{self.path}: the header is corrupt (it fails its checksum): "
                               "the recorded case, burrs, voxel size and oversampling cannot "
                               "be trusted, so the run cannot be rebuilt")
        if self.carries_model:
            try:
                return self._carried_models(check)
            except BonesimError as exc:
                # a damaged /model: today's case files may still build the run
                try:
                    models = self._models_from_files(check)
                except (BonesimError, OSError, ValueError):
                    raise exc from None
                self.model_source = f"the case files ({exc})"
                return models
        return self._models_from_files(check)

    def recorded_burrs(self) -> list:
        """The run's burr table (:class:`~bonesim.io.burrs.Burr`, by index): the
        file's own record when it carries its model, else today's burr files."""
        if self.carries_model:
            from bonesim.io.embedded_case import burr_from_record

            return [burr_from_record(b, f"{self.path}: header model.burrs[{q}]")
                    for q, b in enumerate(self.header["model"]["burrs"])]
        from bonesim.io.burrs import load_burr

        return [load_burr(b["name"]) for b in self.header["burrs"]]

    def case_source(self) -> str:
        """Where today's files for the recorded case are: the recorded manifest
        path while it exists, else the bundled case's name."""
        case = self.header["case"]
        path = case.get("path")
        return path if path and Path(path).exists() else case["name"]

    def device_caps(self):
        """The recorded device limits (header ``device``) as
        :class:`~bonesim.engine.device_caps.DeviceCaps` (JSON null: unlimited)."""
        from bonesim.engine.device_caps import DeviceCaps

        dev = self.header["device"]
        inf = math.inf
        return DeviceCaps(dev["name"], dev["max_force_n"] or inf,
                          tuple(x or inf for x in dev["workspace_mm"]),
                          dev["max_stiffness_n_per_mm"] or inf, dev["rate_hz"])

    def _carried_models(self, check: bool) -> list:
        """The models rebuilt from the file's own record (schema 4)."""
        from dataclasses import replace

        from bonesim.io.embedded import read_volume
        from bonesim.io.embedded_case import embedded_case, materials_from_record
        from bonesim.io.loading import load_model

        h = self.header
        rec = h["model"]
        f, _, _, view = open_session_file(self.path, require_h5py())
        try:
            with f:
                vol = read_volume(self.path, f)
        finally:
            if view is not None:
                view.close()
        case = embedded_case(self.path, rec["case"], vol)
        burrs = self.recorded_burrs()
        m = load_model(case, burrs[0], device=self.device_caps(),
                       oversample=int(h["oversample"]),
                       materials=materials_from_record(rec["materials"]))
        m = replace(m, max_bodies=int(rec.get("max_bodies", m.max_bodies)))
        models = [m] + [m.with_burr(b) for b in burrs[1:]]
        bad = next((q for q, (mm, want) in enumerate(zip(models, h["model_sha256"]))
                    if model_sha256(mm) != want), None) if check else None
        if bad is not None:
            from bonesim import __version__

            raise BonesimError(
                f"{self.path}: burr {bad} ({rec['burrs'][bad]['name']}): the model rebuilt "
                f"from the file's own record does not hash to the recorded one; bonesim "
                f"{__version__} builds the physics differently from the version that "
                f"recorded it ({h.get('bonesim_version', '?')})")
        return models

    def _models_from_files(self, check: bool) -> list:
        """The models rebuilt from today's case and burr files (schemas 1-3)."""
        from bonesim.io.burrs import load_burr
        from bonesim.io.loading import load_model

        h = self.header
        case = h["case"]
        src = self.case_source()
        caps = self.device_caps()
        burrs = []
        for b in h["burrs"]:
            p = b.get("path")
            try:
                burrs.append(load_burr(b["name"]))
            except Exception:
                if p is None:
                    raise
                burrs.append(load_burr(p))
        # the run's voxel, which --voxel-mm may have set over the manifest's
        voxel = h.get("voxel_mm")

        def build(source):
            m = load_model(source, burrs[0], device=caps, oversample=int(h["oversample"]),
                           voxel_mm=None if voxel is None else float(voxel))
            return [m] + [m.with_burr(b) for b in burrs[1:]]

        def mismatch(models):
            return next((q for q, (m, want) in enumerate(zip(models, h["model_sha256"]))
                         if model_sha256(m) != want), None)

        models = build(src)
        if not check:
            return models
        bad = mismatch(models)
        if bad is not None:
            # a bundled case that changed since: the kept older versions, newest
            # first, found by the recorded hashes (also when the recorded
            # manifest path still exists but holds another version: a checkout
            # or install updated in place; today's bundled case is tried first)
            from bonesim.io.case import CASE_FILE, case_versions, cases_dir

            older = case_versions(case["name"])
            today = cases_dir() / case["name"] / CASE_FILE
            first = [None] if older and src != case["name"] and \
                Path(src).resolve() != today.resolve() else []
            for version in first + older:
                candidate = build(case["name"] if version is None else version)
                if mismatch(candidate) is None:
                    self.case_version = version
                    return candidate
        if bad is not None:
            why = ("the case, burr or material files changed since the recording"
                   if self.checksums else
                   "the case, burr or material files changed since the recording, or the "
                   f"header is damaged: schema {self.schema} files carry no checksum to "
                   "tell which")
            raise BonesimError(
                f"{self.path}: burr {bad} ({h['burrs'][bad]['name']}) on case "
                f"{case['name']!r} no longer builds the recorded model ({why})")
        return models

    def load_model(self, check: bool = True):
        """The model of burr 0 (see :meth:`burr_models`)."""
        return self.burr_models(check)[0]


def _no_rows(cols: dict) -> dict:
    """Columns of no rows, of the schema's dtypes and shapes."""
    return {name: np.zeros((0,) + tuple(shape), np.dtype(dt))
            for name, (dt, shape) in cols.items()}


def _check_root(f, path: Path) -> tuple[int, dict, bool]:
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode()
    if fmt != FORMAT:
        raise BonesimError(f"{path}: not a bonesim session (format attribute is "
                           f"{fmt!r}, expected {FORMAT!r})")
    try:
        schema = int(f.attrs["schema"])
    except (KeyError, TypeError, ValueError):
        raise BonesimError(f"{path}: the schema version attribute is missing or not "
                           "an integer") from None
    if schema > SCHEMA_VERSION:
        raise BonesimError(f"{path}: written with session schema {schema}, newer than "
                           f"this bonesim reads ({SCHEMA_VERSION}); upgrade bonesim")
    if schema < 1:
        raise BonesimError(f"{path}: invalid session schema version {schema}")
    header_ok = True
    if schema >= 3:
        try:
            text, want = f.attrs["header"], f.attrs["header_sha256"]
            text = text.decode() if isinstance(text, bytes) else str(text)
            want = want.decode() if isinstance(want, bytes) else str(want)
            header_ok = header_sha256(fmt, schema, text) == want
        except (KeyError, OSError, RuntimeError, UnicodeDecodeError):
            header_ok = False
    try:
        header = json.loads(f.attrs["header"])
    except (KeyError, TypeError, ValueError) as exc:
        what = "" if header_ok else " and fails its checksum (corrupt)"
        raise BonesimError(f"{path}: the header attribute is missing or not JSON{what} "
                           f"({exc})") from None
    if not isinstance(header, dict):
        raise BonesimError(f"{path}: the header is not a JSON object"
                           + ("" if header_ok else " (it fails its checksum: corrupt)"))
    missing = [k for k in HEADER_KEYS if k not in header]
    if missing:
        raise BonesimError(f"{path}: header lacks {', '.join(missing)}"
                           + ("" if header_ok else " (it fails its checksum: corrupt)"))
    return schema, header, header_ok


def _fill(dt, shape, n: int) -> np.ndarray:
    """``n`` rows standing in for a lost column: NaN for floats, else 0."""
    dt = np.dtype(dt)
    return np.full((n,) + tuple(shape), np.nan if dt.kind == "f" else 0, dt)


def _read_group(f, g: str, cols: dict, path: Path, real_size, problems: list, lost: list,
                holes: list):
    """One group's columns, cut to the rows all of them hold; returns the
    columns and the rows the file declares (rows lost to damage noted).

    A column that cannot be opened or read at all is lost alone (``lost``;
    NaN or 0 rows stand in for it); a column a replay needs that reads up to
    a bad chunk cuts the group there (the damage names the chunk); a bad
    chunk of another sample column reads as NaN or 0 (``holes``)."""
    empty = _no_rows(cols)
    try:
        grp = f[g]
        present = set(grp.keys())
    except KeyError:
        raise BonesimError(f"{path}: group /{g} is missing") from None
    except (OSError, RuntimeError) as exc:
        problems.append(f"/{g} unreadable ({exc})")
        return empty, None
    data, declared, cut = {}, 0, False
    gone, named = [], []
    for name, (dt, shape) in cols.items():
        if name not in present:
            raise BonesimError(f"{path}: dataset /{g}/{name} is missing")
        try:
            ds = grp[name]
            if ds.shape[1:] != tuple(shape) or ds.dtype != np.dtype(dt):
                raise BonesimError(
                    f"{path}: dataset /{g}/{name} has shape {ds.shape} and type "
                    f"{ds.dtype}; schema {SCHEMA_VERSION} expects (n, "
                    f"{', '.join(map(str, shape))}) {np.dtype(dt)}".replace("(n, )", "(n,)"))
            data[name], why = read_prefix_why(ds, real_size,
                                              holes=g == "samples" and name not in
                                              REPLAY_COLUMNS)
            declared = max(declared, int(ds.shape[0]))
        except (OSError, RuntimeError, KeyError) as exc:
            gone.append(name)
            problems.append(f"/{g}/{name} unreadable, that column is lost "
                            f"({str(exc).splitlines()[0]})")
            continue
        if why is not None:
            cut |= len(data[name]) < ds.shape[0]
            named.append(f"/{g}/{name}: {why}")
            if "there)" in why:
                holes.append(f"/{g}/{name}")
    if named:                   # one line: the first column's damage, and how many more
        more = len(named) - 1
        problems.append(named[0] + (f" (and {more} more column{'s' * (more > 1)} of /{g})"
                                    if more else ""))
    if not data:                                 # every column lost
        return empty, None
    # a crash between two columns' resizes leaves them uneven: keep the rows
    # every column has
    n = min(len(a) for a in data.values())
    for name in gone:
        lost.append(f"/{g}/{name}")
        data[name] = _fill(*cols[name], n)
    return {k: data[k][:n] for k in cols}, (declared if cut else None)


def _cut_to_one_moment(groups: dict, declared: dict, whole: str) -> None:
    """Cut every stream of a damaged file at the moment its sample or removal
    stream stops being readable: samples up to the last readable one, and
    nothing from the step of the last readable removal on (that step's other
    removals may be lost)."""
    upto, before = math.inf, math.inf
    if declared.get("samples") is not None:
        t = groups["samples"]["t_s"]
        upto = float(t[-1]) if len(t) else -math.inf
    if declared.get(whole) is not None:
        t = groups[whole]["t_s"]
        before = float(t[-1]) if len(t) else -math.inf
    if upto == math.inf and before == math.inf:
        return
    for g in groups:
        t = groups[g]["t_s"]
        keep = np.isnan(t) | ((t <= upto) & (t < before))   # NaN: the writer's notes
        if not keep.all():
            groups[g] = {k: a[keep] for k, a in groups[g].items()}


def _check_sample_times(groups: dict, declared: dict, problems: list) -> None:
    """Sample times must be finite and strictly increasing: a file whose times
    stop being so is damaged from that row on (kept: the rows before)."""
    t = groups["samples"]["t_s"]
    if not len(t):
        return
    ok = np.isfinite(t)
    ok[1:] &= np.diff(t) > 0
    if ok.all():
        return
    q = int(np.argmin(ok))
    what = (f"sample time {t[q]!r} is not finite" if not np.isfinite(t[q]) else
            f"sample times go backwards ({t[q - 1]:.6g} s then {t[q]:.6g} s)")
    problems.append(f"/samples/t_s: {what} at row {q:,}")
    declared["samples"] = max(declared.get("samples") or 0, len(t))
    groups["samples"] = {k: a[:q] for k, a in groups["samples"].items()}


def read_session(path) -> Session:
    """Read and check a session file.

    A damaged file is read up to where it stops being readable (see the
    module's notes); :attr:`Session.damage` says what is wrong.

    Raises
    ------
    BonesimError
        Naming the file and the problem: missing, empty, not HDF5, not a
        bonesim session, written by a newer schema, a missing or malformed
        header field, group or column, or damaged beyond reading.
    """
    path = Path(path)
    if is_compaction_temp(path):
        target = path.with_name(path.name[1:-len(".compacting")])
        raise BonesimError(f"{path}: a leftover of an interrupted compaction of {target.name}, "
                           f"not a session ({target.name} holds the recording); delete it")
    f, damage, real_size, view = open_session_file(path, require_h5py())
    problems = [damage] if damage else []
    lost: list = []
    holes: list = []
    try:
        with f:
            schema, header, header_ok = _check_root(f, path)
            if not header_ok:
                problems.insert(0, "the header is corrupt: it fails its checksum")
            try:
                repaired = json.loads(f.attrs["repaired"]) if "repaired" in f.attrs \
                    else None
            except (TypeError, ValueError):
                repaired = None
            spec, whole = _SCHEMAS[schema]
            carries = MODEL_GROUP in f and "model" in header
            groups, declared = {}, {}
            for g, cols in spec.items():
                if g in OPTIONAL_GROUPS and g not in f:      # written before it existed
                    groups[g], declared[g] = _no_rows(cols), None
                    continue
                groups[g], declared[g] = _read_group(f, g, cols, path, real_size, problems,
                                                     lost, holes)
            try:
                closed = read_prefix(f["closed"], real_size)
                complete = bool(len(closed) and closed[0] == 1)
            except (KeyError, OSError, RuntimeError):
                complete = False
    except (OSError, RuntimeError, KeyError) as exc:    # the root itself is lost
        what = f"{damage}: " if damage else ""
        raise BonesimError(f"{path}: damaged beyond reading ({what}"
                           f"{str(exc).strip(chr(39))})") from None
    finally:
        if view is not None:
            view.close()
    _check_sample_times(groups, declared, problems)
    readable = {}
    if problems:
        rows_before = {g: len(groups[g]["t_s"]) for g in spec}
        _cut_to_one_moment(groups, declared, whole)
        for g in spec:
            if declared[g] is not None or len(groups[g]["t_s"]) < rows_before[g]:
                total = declared[g] if declared[g] is not None else rows_before[g]
                readable[g] = (int(len(groups[g]["t_s"])), int(total))
        complete = False
    ev = groups["events"]
    evlist = [(float(t), n.decode(errors="replace"), v.decode(errors="replace"))
              for t, n, v in zip(ev["t_s"], ev["name"], ev["value"])]
    stopped = next((v for _, n, v in evlist if n == "stopped"), None)
    if schema == 1:
        tissue, evlist = migrate_v1(groups["removals"], groups["injuries"], evlist)
    else:
        tissue = groups["tissue"]
    return Session(path, schema, header, complete, groups["samples"], tissue,
                   groups["camera"], evlist, "; ".join(problems) or None, readable,
                   repaired, groups.get("handle", _no_rows(GROUPS["handle"])),
                   header_ok=header_ok, checksums=schema >= 3, lost=lost, stopped=stopped,
                   holes=holes, carries_model=carries)


def damage_notice(session: Session) -> str | None:
    """One line for a damaged session: what is wrong and what is used."""
    if session.damage is None:
        return None
    t = session.samples["t_s"]
    upto = f"its first {float(t[-1] - t[0]):.1f} s" if len(t) else "no samples"
    return f"{session.path}: damaged ({session.damage}); using the readable part: {upto}"


def repair_session(path, out, overwrite: bool = False) -> Session:
    """Write the readable part of a (damaged) session as a clean file.

    Parameters
    ----------
    path : path
        The session file to read (:func:`read_session`).
    out : path
        New file (compacted, closed; an existing one only with ``overwrite``).
        Its ``repaired`` root attribute records the source and its damage.
    overwrite : bool

    Returns
    -------
    Session
        ``out`` read back.
    """
    src = read_session(path)
    out = Path(out)
    if out.resolve() == Path(path).resolve():
        raise BonesimError(f"{out}: the repaired copy must be a new file, not the one "
                           "read")
    if not src.header_ok:
        raise BonesimError(f"{path}: the header is corrupt (it fails its checksum); a "
                           "repaired copy would carry a header that cannot be trusted")
    if not len(src.samples["t_s"]):
        raise BonesimError(f"{path}: nothing readable to repair (no samples"
                           + (f"; {src.damage})" if src.damage else ")"))
    if src.lost:
        raise BonesimError(f"{path}: column{'s' if len(src.lost) > 1 else ''} "
                           f"{', '.join(src.lost)} lost; a repaired copy would hold stand-in "
                           "values for them")
    groups = {"samples": src.samples, "tissue": src.tissue, "camera": src.camera,
              "handle": src.handle}
    ev = src.events
    groups["events"] = {"t_s": np.array([e[0] for e in ev], np.float64),
                        "name": np.array([e[1].encode() for e in ev],
                                         GROUPS["events"]["name"][0]),
                        "value": np.array([e[2].encode() for e in ev],
                                          GROUPS["events"]["value"][0])}
    with SessionWriter(out, src.header, overwrite=overwrite, compact=False) as w:
        for g, cols in groups.items():
            w.append(g, cols)
    if w.failed is not None:                     # a full disk: no half copy left behind
        out.unlink(missing_ok=True)
        raise BonesimError(f"{out}: the repaired copy could not be written: {w.failed}")
    with require_h5py().File(out, "r+") as f:           # attributes cannot change under SWMR
        f.attrs["repaired"] = json.dumps({"from": str(Path(path)), "damage": src.damage})
    compact_session(out)
    return read_session(out)


def session_info(session: Session) -> dict:
    """JSON-ready summary of a session (``bonesim sessions info``)."""
    h = session.header
    s = session.samples
    t = s["t_s"]
    names = {st["label"]: st["name"] for st in h["structures"]}
    labels, counts = np.unique(session.removals["label"], return_counts=True)
    dt = np.diff(t)
    inj = session.injuries
    vis = session.removals["visible"]
    n_vis, n_hid = int(np.sum(vis == 1)), int(np.sum(vis == 0))
    return {
        "file": str(session.path),
        "size_bytes": session.path.stat().st_size,
        "schema": session.schema,
        "complete": session.complete,
        "damage": session.damage,
        "checksums": "header and every chunk" if session.checksums
        else f"none (schema {session.schema})",
        "header_ok": session.header_ok,
        "lost_columns": session.lost or None,
        "columns_with_holes": session.holes or None,
        "stopped": session.stopped,
        "repaired_from": session.repaired,
        "readable_rows": {g: {"kept": k, "declared": d}
                          for g, (k, d) in session.readable.items()} or None,
        "recorded_with": h["bonesim_version"],
        "start_time": h["start_time"],
        "participant": h["participant"], "group": h["group"], "notes": h["notes"],
        "case": h["case"]["name"],
        "burrs": [b["name"] for b in h["burrs"]],
        "device": h["device"]["name"],
        "voxel_mm": h["voxel_mm"],
        "duration_s": round(session.duration_s, 3),
        "samples": int(len(t)),
        "sample_rate_hz": round(float(1.0 / np.median(dt)), 1)
        if len(dt) and np.median(dt) > 0 else 0.0,
        "resets": int(s["epoch"][-1]) if len(t) else 0,
        "drill_on_s": round(float(np.sum(dt[s["drill"][:-1] > 0])), 3) if len(dt) else 0.0,
        "max_force_n": round(float(np.nanmax(np.linalg.norm(s["force_n"], axis=1))), 3)
        if len(t) and not np.isnan(s["force_n"]).all() else 0.0,
        "voxels_removed": int(len(session.removals["t_s"])),
        "removed_by_structure": {names.get(int(lab), str(int(lab))): int(c)
                                 for lab, c in zip(labels, counts)},
        # removals seen from the eye, of those judged (SPEC: voxel visibility)
        "removals_visible": n_vis, "removals_hidden": n_hid,
        "removals_visibility_unknown": int(len(vis)) - n_vis - n_hid,
        "visible_fraction": round(n_vis / (n_vis + n_hid), 4) if n_vis + n_hid else None,
        "injuries": [{"t_s": round(float(ti), 4),
                      "structure": names.get(int(lab), str(int(lab))),
                      "kind": events.INJURY_KINDS[int(k)] if int(k) < 2 else str(int(k))}
                     for ti, lab, k in zip(inj["t_s"], inj["label"], inj["kind"])],
        "camera_frames": int(len(session.camera["t_s"])),
        "self_contained": session.carries_model,
        "events": len(session.events),
    }


def list_sessions(folder=None) -> list[dict]:
    """One row per ``*.h5`` file in ``folder`` (default :func:`sessions_folder`),
    newest first; unreadable files are listed with their error."""
    folder = sessions_folder() if folder is None else Path(folder)
    if not folder.is_dir():
        raise BonesimError(f"{folder}: no such sessions folder")
    rows = []
    files = list(folder.glob("*.h5")) + list(folder.glob(".*.h5.compacting"))
    for p in sorted(files, key=lambda q: q.stat().st_mtime, reverse=True):
        try:
            info = session_info(read_session(p))
            rows.append({k: info[k] for k in ("file", "start_time", "participant", "group",
                                               "case", "duration_s", "voxels_removed",
                                               "complete", "damage")}
                        | {"injuries": len(info["injuries"])})
        except BonesimError as exc:
            rows.append({"file": str(p), "error": str(exc)})
    return rows
