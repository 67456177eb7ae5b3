"""A session's identity: content hashes of what it was recorded on, the
header that names them, the header's own checksum, and where files go.

The header (root attribute ``header``, JSON; ``docs/session_schema.md``)
names the case, burrs and device a run was recorded with and hashes of
each, so that a reader can tell whether today's files still build the
recorded model (:func:`model_sha256`). :func:`header_sha256` is the
checksum stored beside it (root attribute ``header_sha256``).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["case_sha256", "recorded_case_sha256", "burr_sha256", "model_sha256",
           "header_sha256", "make_header", "model_record", "recorded_volume",
           "sessions_folder", "default_session_path"]


def _hash_path(h, path: Path) -> None:
    if path.is_dir():
        for p in sorted(q for q in path.rglob("*") if q.is_file()):
            h.update(str(p.relative_to(path)).encode())
            h.update(p.read_bytes())
    elif path.is_file():
        h.update(path.read_bytes())


def case_sha256(case) -> str:
    """Content hash of a case: its manifest and the volume files it names
    (for a case a session file carries, the hash recorded there)."""
    from bonesim.io.embedded import SESSION_FORMAT

    if case.volume.format == SESSION_FORMAT:
        return recorded_case_sha256(case.manifest)
    h = hashlib.sha256()
    h.update(Path(case.manifest).read_bytes())
    for p in (case.volume.path, case.volume.labels):
        if p is not None:
            _hash_path(h, Path(p))
    return h.hexdigest()


def recorded_case_sha256(path) -> str | None:
    """The case hash a session file's header records (None if it has none)."""
    from bonesim.session.schema import require_h5py

    with require_h5py().File(path, "r") as f:
        text = f.attrs.get("header", "{}")
    text = text.decode() if isinstance(text, bytes) else str(text)
    return json.loads(text).get("case", {}).get("sha256")


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
    bud = model.budget
    if bud is not None and bud.binding:
        # the fixed-budget step's removal cells and budget (the models where it
        # does not bind hash as they always did)
        h.update(np.array([bud.cell, bud.removal_voxels[0]], np.int64).tobytes())
        h.update(np.ascontiguousarray(bud.lat[0]).tobytes())
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
    if case is not None:
        head["model"] = model_record(model, burrs)
    if device_record is not None:
        head["device_record"] = json.loads(json.dumps(device_record))   # JSON-ready now
    return head


def model_record(model, burrs=()) -> dict:
    """What rebuilds ``model`` (burr 0) and ``burrs`` besides the tissue arrays
    (:func:`bonesim.io.embedded.write_volume`): the case record, the burr table
    with every value, the materials per kind and the body limit (header key
    ``model``; the oversampling, device limits and rate are the header's)."""
    from bonesim.io.embedded_case import burr_record, case_record, materials_record

    return {"case": case_record(model.case, model.spacing_mm),
            "burrs": [burr_record(b) for b in [model.burr] + list(burrs)],
            "materials": materials_record(model),
            "max_bodies": int(model.max_bodies)}


def recorded_volume(model, header: dict):
    """The initial tissue a session of ``model`` with ``header`` stores (its
    case's volume, loaded again: :class:`~bonesim.io.volumes.CaseVolume`), or
    None for a model built from arrays or a header without a ``model`` record.
    Checked against the model's grid."""
    case = model.case
    if case is None or "model" not in header:
        return None
    vol = case.load_volume()
    g = model.grid
    if tuple(vol.labels.shape) != tuple(g.shape) or float(vol.spacing_mm) != g.spacing_mm \
            or not np.array_equal(vol.origin_mm, np.asarray(g.origin_mm, float)):
        raise ValueError(f"case {case.name!r} no longer loads the grid its model was "
                         "built on; the session cannot store it")
    return vol


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


def header_sha256(fmt: str, schema: int, header_json: str) -> str:
    """Checksum of a file's identity attributes: ``format``, ``schema`` and the
    header's JSON text, as stored (schema 3: the root attribute ``header_sha256``)."""
    h = hashlib.sha256()
    for part in (str(fmt), str(int(schema)), header_json):
        b = part.encode("utf-8", "surrogateescape")    # a flipped byte stays a byte
        h.update(len(b).to_bytes(8, "little") + b)
    return h.hexdigest()
