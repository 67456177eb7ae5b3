"""Writing and reading vision datasets: one chunked, compressed HDF5 file, or
a folder of PNG / TIFF images with a JSON index (``docs/dataset_format.md``).

Both are written so that the same content gives the same bytes: no times in
the HDF5 objects (``track_times=False``), fixed chunking and compression,
attributes as key-sorted JSON, PNGs and TIFFs without dates.

:func:`open_writer` picks the writer from the output's name; :func:`open_dataset`
reads either back (:class:`Dataset`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.session import dataset_spec as spec

__all__ = ["FRAME_COLUMNS", "STREAMS", "H5_SUFFIXES", "GZIP_LEVEL", "open_writer",
           "H5Writer", "FolderWriter", "Dataset", "open_dataset"]

#: Per-frame columns: name -> (dtype, trailing shape).
FRAME_COLUMNS = {
    "t_s": (np.float64, ()), "session_t_s": (np.float64, ()), "sample": (np.int64, ()),
    "epoch": (np.int32, ()), "tool_pos_mm": (np.float64, (3,)),
    "tool_axis": (np.float64, (3,)), "burr": (np.uint8, ()),
    "burr_radius_mm": (np.float64, ()), "drill": (np.uint8, ()),
    "speed_rpm": (np.float64, ()), "direction": (np.int8, ()), "force_n": (np.float64, ()),
    "removed_voxels": (np.int64, ()), "suction_tip_mm": (np.float64, (3,)),
    "irrigation": (np.uint8, ()),
}
#: Per-eye image streams: name -> (dtype, channels or None, option that asks for it).
STREAMS = {
    "rgb": (np.uint8, 3, "rgb"), "depth": (np.float32, None, "depth"),
    "class": (np.uint8, None, "seg"), "instance": (np.int16, None, "seg"),
    "normals": (np.float32, 3, "normals"), "points_cam": (np.float32, 3, "points"),
    "points_case": (np.float32, 3, "points"),
}
#: Camera columns per eye: name -> trailing shape.
CAMERA_COLUMNS = {"K": (3, 3), "R": (3, 3), "t": (3,), "cam_to_case": (4, 4),
                  "eye_mm": (3,), "focal_mm": (3,), "up": (3,)}
H5_SUFFIXES = (".h5", ".hdf5")
#: gzip level of every stream (with byte shuffle).
GZIP_LEVEL = 4


def _streams(options) -> list[str]:
    d = options.to_dict()
    return [s for s, (_, _, opt) in STREAMS.items() if d[opt]]


def open_writer(out, options, n_frames: int, classes, provenance: dict, burrs):
    """The writer for ``out``: :class:`H5Writer` for ``*.h5`` / ``*.hdf5``,
    :class:`FolderWriter` otherwise."""
    out = Path(out)
    cls = H5Writer if out.suffix.lower() in H5_SUFFIXES else FolderWriter
    return cls(out, options, n_frames, classes, provenance, burrs)


def _root_attrs(options, n_frames, classes, provenance, burrs) -> dict:
    w, h = options.size
    return {"format": spec.FORMAT, "version": spec.VERSION, "frames": int(n_frames),
            "size": [int(w), int(h)], "eyes": list(options.eyes),
            "baseline_mm": float(options.stereo_mm or 0.0), "streams": _streams(options),
            "classes": classes, "burrs": list(burrs), "provenance": provenance,
            "options": options.to_dict()}


class H5Writer:
    """One HDF5 file (see the module docstring); written frame by frame."""

    def __init__(self, path, options, n_frames, classes, provenance, burrs):
        import h5py

        self.path = Path(path)
        if self.path.is_dir():
            raise BonesimError("is a folder; give a file name ending in .h5", self.path)
        if not self.path.parent.is_dir():
            raise BonesimError("the output folder does not exist", self.path)
        self.tmp = self.path.with_name(self.path.name + ".part")
        try:
            self.f = h5py.File(self.tmp, "w", libver=("earliest", "v110"), track_order=False)
        except OSError as exc:
            raise BonesimError(f"cannot write the dataset: {exc}", self.path) from None
        self.options = options
        n = int(n_frames)
        w, h = options.size
        f = self.f
        attrs = _root_attrs(options, n, classes, provenance, burrs)
        for k, v in attrs.items():
            f.attrs[k] = v if isinstance(v, (int, float, str)) else spec.to_json(v)
        g = f.create_group("frames", track_order=False)
        for name, (dt, shape) in FRAME_COLUMNS.items():
            g.create_dataset(name, shape=(n,) + shape, dtype=dt, track_times=False)
        self.streams = _streams(options)
        for eye in options.eyes:
            ge = f.create_group(eye, track_order=False)
            gc = ge.create_group("camera", track_order=False)
            for name, shape in CAMERA_COLUMNS.items():
                gc.create_dataset(name, shape=(n,) + shape, dtype=np.float64,
                                  track_times=False)
            for s in self.streams:
                dt, ch, _ = STREAMS[s]
                shape = (n, h, w) + ((ch,) if ch else ())
                fill = np.nan if np.dtype(dt).kind == "f" else 0
                ge.create_dataset(s, shape=shape, dtype=dt, chunks=(1,) + shape[1:],
                                  compression="gzip", compression_opts=GZIP_LEVEL,
                                  shuffle=True, fillvalue=fill, track_times=False)

    def write(self, i: int, record: dict, eyes: list) -> None:
        g = self.f["frames"]
        for name in FRAME_COLUMNS:
            g[name][i] = record[name]
        for eye, res in zip(self.options.eyes, eyes):
            ge = self.f[eye]
            for name in CAMERA_COLUMNS:
                ge["camera"][name][i] = res["camera"][name]
            for s in self.streams:
                ge[s][i] = res[s]

    def close(self, ok: bool = True) -> None:
        if self.f is None:
            return
        self.f.close()
        self.f = None
        if ok:
            self.tmp.replace(self.path)
        else:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *_):
        self.close(ok=exc_type is None)


def _png(path: Path, arr: np.ndarray) -> None:
    from PIL import Image

    img = Image.fromarray(np.ascontiguousarray(arr))       # uint16 -> "I;16", 16-bit PNG
    img.save(path, format="PNG", optimize=False, compress_level=6)


def _tiff(path: Path, arr: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(arr, np.float32)).save(            # mode "F"
        path, format="TIFF", compression="tiff_adobe_deflate")


class FolderWriter:
    """A folder of images and ``index.json`` (see ``docs/dataset_format.md``):

    ``<eye>/rgb/NNNNNN.png`` (8-bit RGB), ``<eye>/depth/NNNNNN.tiff`` (32-bit
    float [mm], NaN nothing), ``<eye>/class/NNNNNN.png`` (8-bit),
    ``<eye>/instance/NNNNNN.png`` (16-bit, the instance plus one: 0 none),
    ``<eye>/normals|points_cam|points_case/NNNNNN.npy`` (float32 (H, W, 3)).
    """

    EXT = {"rgb": ".png", "depth": ".tiff", "class": ".png", "instance": ".png",
           "normals": ".npy", "points_cam": ".npy", "points_case": ".npy"}

    def __init__(self, path, options, n_frames, classes, provenance, burrs):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise BonesimError("exists and is not a folder", self.path)
        if self.path.is_dir() and any(self.path.iterdir()):
            raise BonesimError("the folder is not empty; choose a new or empty one", self.path)
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BonesimError(f"cannot create the folder: {exc.strerror or exc}",
                               self.path) from None
        self.options = options
        self.streams = _streams(options)
        for eye in options.eyes:
            for s in self.streams:
                (self.path / eye / s).mkdir(parents=True, exist_ok=True)
        self.index = _root_attrs(options, n_frames, classes, provenance, burrs)
        self.index["frame_records"] = [None] * int(n_frames)

    def write(self, i: int, record: dict, eyes: list) -> None:
        rec = {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v)
               for k, v in record.items()}
        rec["suction_tip_mm"] = [None if x != x else x for x in rec["suction_tip_mm"]]
        rec["files"], rec["camera"] = {}, {}
        for eye, res in zip(self.options.eyes, eyes):
            rec["camera"][eye] = {k: np.asarray(res["camera"][k]).tolist()
                                  for k in CAMERA_COLUMNS}
            files = {}
            for s in self.streams:
                rel = f"{eye}/{s}/{i:06d}{self.EXT[s]}"
                a = res[s]
                if s == "depth":
                    _tiff(self.path / rel, a)
                elif s == "instance":
                    _png(self.path / rel, (a.astype(np.int32) + 1).astype(np.uint16))
                elif self.EXT[s] == ".npy":
                    np.save(self.path / rel, np.ascontiguousarray(a, np.float32))
                else:
                    _png(self.path / rel, np.ascontiguousarray(a))
                files[s] = rel
            rec["files"][eye] = files
        self.index["frame_records"][i] = rec

    def close(self, ok: bool = True) -> None:
        if ok and self.index is not None:
            (self.path / "index.json").write_text(
                json.dumps(self.index, sort_keys=True, indent=1) + "\n", encoding="utf-8")
        self.index = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *_):
        self.close(ok=exc_type is None)


# ------------------------------------------------------------------ reading
class Dataset:
    """A dataset read back (either layout).

    Attributes
    ----------
    attrs : dict
        ``format``, ``version``, ``frames``, ``size``, ``eyes``,
        ``baseline_mm``, ``streams``, ``classes``, ``burrs``, ``provenance``,
        ``options``.
    frames : dict of ndarray
        The per-frame columns (:data:`FRAME_COLUMNS`).
    """

    def __init__(self, path):
        self.path = Path(path)
        self._h5 = None
        try:
            if self.path.is_dir():
                idx = json.loads((self.path / "index.json").read_text(encoding="utf-8"))
                recs = idx.pop("frame_records")
                self.attrs = idx
                self._recs = recs
                self.frames = {}
                for name, (dt, _) in FRAME_COLUMNS.items():
                    vals = [r[name] for r in recs]
                    if name == "suction_tip_mm":
                        vals = [[np.nan if x is None else x for x in v] for v in vals]
                    self.frames[name] = np.asarray(vals, dtype=dt)
            else:
                import h5py

                self._h5 = h5py.File(self.path, "r")
                a = dict(self._h5.attrs)
                self.attrs = {k: (json.loads(v) if k in ("size", "eyes", "streams", "classes",
                                                          "burrs", "provenance", "options")
                                  else v) for k, v in a.items()}
                self.frames = {k: self._h5["frames"][k][()] for k in FRAME_COLUMNS}
        except (OSError, ValueError, KeyError) as exc:
            raise BonesimError(f"not a readable bonesim dataset: {exc}", self.path) from None
        if self.attrs.get("format") != spec.FORMAT:
            raise BonesimError(f"not a bonesim dataset (format {self.attrs.get('format')!r})",
                               self.path)

    def __len__(self) -> int:
        return int(self.attrs["frames"])

    def camera(self, i: int, eye: str = "left") -> dict:
        """Frame ``i``'s camera: ``K``, ``R``, ``t``, ``cam_to_case``, ..."""
        if self._h5 is not None:
            g = self._h5[eye]["camera"]
            return {k: g[k][i] for k in CAMERA_COLUMNS}
        return {k: np.asarray(v) for k, v in self._recs[i]["camera"][eye].items()}

    def frame(self, i: int, eye: str = "left") -> dict:
        """Frame ``i``'s streams for ``eye`` (as the renderer gave them)."""
        out = {}
        for s in self.attrs["streams"]:
            if self._h5 is not None:
                out[s] = self._h5[eye][s][i]
                continue
            p = self.path / self._recs[i]["files"][eye][s]
            if p.suffix == ".npy":
                out[s] = np.load(p)
            else:
                from PIL import Image

                with Image.open(p) as img:
                    a = np.array(img)
                if s == "instance":
                    a = (a.astype(np.int32) - 1).astype(np.int16)
                out[s] = a
        return out

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_dataset(path) -> Dataset:
    """Read a dataset file or folder (one line naming it if it is not one)."""
    p = Path(path)
    if not p.exists():
        raise BonesimError("no such file or folder", p)
    return Dataset(p)
