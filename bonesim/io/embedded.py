"""The tissue a session file carries: the initial label grids of the case a
run was recorded on, stored in the file and read back as a case volume.

A session file (schema 4, ``docs/session_schema.md``) holds, in its group
``/model``, the initial tissue as the run loaded it: the engine's label grid
(``labels``, uint8, axes x, y, z of the LPS case frame) and, when the source
had another resolution, the source-resolution label map the distances are
measured on (``native_labels``), each with its ``spacing_mm`` and
``origin_mm``. The rest of what rebuilds the model is the header's ``model``
record (:mod:`bonesim.io.embedded_case`). A case whose volume has the format
:data:`SESSION_FORMAT` reads its volume here (:func:`read_volume`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["SESSION_FORMAT", "MODEL_GROUP", "write_volume", "read_volume"]

#: Volume format of a case rebuilt from a session file.
SESSION_FORMAT = "session"
#: The session file's group holding the initial tissue arrays.
MODEL_GROUP = "model"
#: gzip level of the stored label maps (labels compress ~30x: the phantom's
#: 104^3 grid takes 30 kB).
_GZIP = 4


def write_volume(f, vol, name: str) -> None:
    """Store ``vol``'s label grids (a :class:`~bonesim.io.volumes.CaseVolume` of
    case ``name``) in the group :data:`MODEL_GROUP` of the open HDF5 file
    ``f``, compressed and checksummed, each with its ``spacing_mm`` and
    ``origin_mm``."""
    g = f.require_group(MODEL_GROUP)
    g.attrs["case"] = str(name)
    kw = {"compression": "gzip", "compression_opts": _GZIP, "fletcher32": True}
    d = g.create_dataset("labels", data=np.ascontiguousarray(vol.labels, np.uint8), **kw)
    d.attrs["spacing_mm"] = np.full(3, float(vol.spacing_mm))
    d.attrs["origin_mm"] = np.asarray(vol.origin_mm, np.float64)
    if vol.native is not None:
        d = g.create_dataset("native_labels",
                             data=np.ascontiguousarray(vol.native.labels, np.uint8), **kw)
        d.attrs["spacing_mm"] = np.asarray(vol.native.spacing_mm, np.float64)
        d.attrs["origin_mm"] = np.asarray(vol.native.origin_mm, np.float64)


def read_volume(path, f=None):
    """The :class:`~bonesim.io.volumes.CaseVolume` stored in the session file
    ``path`` by :func:`write_volume`; ``f``: the file already open (a reader
    that opened a damaged or still-open file its own way), else it is opened
    here.

    Raises
    ------
    BonesimError
        Naming the file and what is missing or unreadable.
    """
    path = Path(path)
    if f is not None:
        return _read(f, path)
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return _read(f, path)
    except OSError as exc:
        raise BonesimError(f"{path}: /{MODEL_GROUP}: cannot read the recorded case "
                           f"({exc})") from None


def _read(f, path: Path):
    from bonesim.io.volumes import CaseVolume, NativeLabels

    where = f"{path}: /{MODEL_GROUP}"
    try:
        g = f.get(MODEL_GROUP)
        if g is None or "labels" not in g:
            raise BonesimError(f"{where}/labels is missing: the file does not hold "
                               "the case it was recorded on")
        arrays = {}
        for key in ("labels", "native_labels"):
            if key in g:
                d = g[key]
                arrays[key] = (d[()], np.asarray(d.attrs["spacing_mm"], np.float64),
                               np.asarray(d.attrs["origin_mm"], np.float64))
        name = str(g.attrs.get("case", "?"))
    except (OSError, KeyError, RuntimeError) as exc:
        raise BonesimError(f"{where}: cannot read the recorded case "
                           f"({type(exc).__name__}: {exc})") from None
    for key, (a, sp, org) in arrays.items():
        if a.ndim != 3 or a.dtype != np.uint8 or sp.shape != (3,) or org.shape != (3,) \
                or not np.all(np.isfinite(sp) & (sp > 0)) or not np.all(np.isfinite(org)):
            raise BonesimError(f"{where}/{key} is not a 3-D uint8 label map with a "
                               f"positive spacing and a finite origin ({a.dtype} {a.shape})")
    labels, sp, org = arrays["labels"]
    if not np.all(sp == sp[0]):
        raise BonesimError(f"{where}/labels: the engine grid must be isotropic, "
                           f"spacing {sp.tolist()} mm")
    native = arrays.get("native_labels")
    return CaseVolume(labels, float(sp[0]), org, f"{path} (recorded case {name!r})",
                      native=None if native is None else NativeLabels(*native))
