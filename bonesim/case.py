"""Cases: a manifest (``case.toml``) naming a volume, its structures, the camera
start and the procedure's target.

Manifest
--------
.. code-block:: toml

    [case]
    name = "phantom"                  # required
    description = "..."               # optional
    side = "left"                     # "left" | "right"

    [volume]
    format = "nrrd"                   # phantom | dicom | nrrd | nifti | label-stack
    path = "ct.nrrd"                  # relative to this manifest (not for phantom)
    voxel_mm = 0.5                    # isotropic output voxel edge, default 0.5
    bone_threshold_hu = 300           # dicom / nrrd / nifti, default 300
    labels = "labels.nrrd"            # dicom / nrrd / nifti: optional label map
    # label-stack only:
    #   pattern = "*.png"  size_mm = [x, y, z]  unknown_colors = "error"
    #   origin_mm = [x, y, z]   (centre of the first voxel; default centred)
    # phantom only:
    #   seed = 0  size_mm = [52, 52, 52]

    [[structures]]                    # order = label index 1, 2, ...
    name = "bone"
    kind = "bone"                     # bone | critical | soft
    label = 1                         # label-map integer (intensity formats)
    color = [230, 220, 200]           # label-stack colour (label-stack: required)
    display_color = [230, 220, 200]   # rendering colour, default from a palette
    monitor = false                   # nerve monitor watches it (not for kind bone)

    [camera]                          # case frame (LPS), mm
    eye_mm = [120, 0, 0]
    focal_mm = [15, 0, 0]
    up = [0, 0, 1]

    [target]                          # optional
    description = "cortical mastoidectomy"
    structures = ["sigmoid_sinus"]    # structures the procedure should expose
    box_mm = [[5, -8, -14], [20, 14, 11]]   # region expected to be drilled

For NRRD and NIfTI, ``path`` may be left out when ``labels`` alone gives all
structures (a label-only case). For the phantom, structure names must be
phantom parts (:data:`bonesim.phantom.PARTS`); parts not listed stay empty.

Every problem is raised as a :class:`~bonesim.errors.BonesimError` naming the
manifest and the offending key.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import phantom as _phantom
from .errors import BonesimError
from .tomlfile import check_keys, get_number, get_str, get_vector, read_toml
from .volumes import (FORMATS, MAX_STRUCTURES, UNKNOWN_COLOR_MODES, CaseVolume,
                      load_volume, write_dicom_series, write_label_stack,
                      write_nifti, write_nrrd)

CASE_FILE = "case.toml"
SIDES = ("left", "right")
KINDS = ("bone", "critical", "soft")
EXPORT_FORMATS = ("dicom", "nrrd", "nifti", "label-stack")
DEFAULT_VOXEL_MM = 0.5
DEFAULT_BONE_THRESHOLD_HU = 300.0
DEFAULT_PATTERN = "*.png"
MIN_VOXEL_MM = 0.01
MAX_VOXEL_MM = 10.0
MAX_LABEL = 65535                     # label maps are at most 16-bit
PALETTE = ((230, 220, 200), (60, 80, 220), (220, 120, 120), (240, 160, 160),
           (250, 230, 40), (60, 210, 90), (200, 100, 230), (250, 250, 250),
           (240, 140, 40), (40, 200, 220), (150, 90, 40), (120, 120, 250))
"""Default display colours, by structure position (cycled)."""
EXPORT_HU_BY_KIND = {"bone": 1500.0, "critical": 40.0, "soft": 40.0}
"""HU written for label-only volumes exported to an intensity format."""
EMPTY_HU = -1000.0

_TOP_KEYS = ("case", "volume", "structures", "camera", "target")
_CASE_KEYS = ("name", "description", "side")
_VOLUME_COMMON = ("format", "voxel_mm")
_VOLUME_KEYS = {
    "phantom": ("seed", "size_mm"),
    "dicom": ("path", "bone_threshold_hu", "labels"),
    "nrrd": ("path", "bone_threshold_hu", "labels"),
    "nifti": ("path", "bone_threshold_hu", "labels"),
    "label-stack": ("path", "pattern", "size_mm", "unknown_colors", "origin_mm"),
}
_STRUCTURE_KEYS = ("name", "kind", "label", "color", "display_color", "monitor")
_CAMERA_KEYS = ("eye_mm", "focal_mm", "up")
_TARGET_KEYS = ("description", "structures", "box_mm")


# ------------------------------------------------------------------ records
@dataclass(frozen=True)
class Structure:
    """One labelled structure of a case.

    Attributes
    ----------
    name : str
        Unique name (e.g. ``"facial_nerve"``).
    kind : str
        ``"bone"`` (drillable bone), ``"critical"`` (must not be injured) or
        ``"soft"`` (soft tissue: dura, sinus, ...).
    label : int or None
        Integer of this structure in a label map.
    color : (3,) int or None
        RGB of this structure in a label stack.
    display_color : (3,) int
        RGB used for rendering, 0-255.
    monitor : bool
        The nerve monitor (:mod:`bonesim.monitor`) reports the simulated
        activity of this structure (nerves such as the facial nerve).
    """

    name: str
    kind: str
    label: int | None
    color: tuple[int, int, int] | None
    display_color: tuple[int, int, int]
    monitor: bool = False


@dataclass(frozen=True)
class VolumeSpec:
    """The ``[volume]`` table, paths resolved against the manifest's folder.

    Attributes
    ----------
    format : str
        One of :data:`bonesim.volumes.FORMATS`.
    path : Path or None
        Volume file / folder (None for the phantom and label-only cases).
    voxel_mm : float
        Isotropic voxel edge after loading [mm].
    bone_threshold_hu : float
        Bone threshold of intensity formats [HU].
    labels : Path or None
        Label map (NRRD / NIfTI).
    pattern : str
        Label-stack glob.
    size_mm : (3,) float or None
        Label-stack or phantom extent ``(x, y, z)`` [mm].
    unknown_colors : str
        Label-stack policy for stray colours.
    origin_mm : (3,) float or None
        Label-stack centre of voxel (0, 0, 0) [mm].
    seed : int
        Phantom seed.
    """

    format: str
    path: Path | None = None
    voxel_mm: float = DEFAULT_VOXEL_MM
    bone_threshold_hu: float = DEFAULT_BONE_THRESHOLD_HU
    labels: Path | None = None
    pattern: str = DEFAULT_PATTERN
    size_mm: tuple[float, float, float] | None = None
    unknown_colors: str = "error"
    origin_mm: tuple[float, float, float] | None = None
    seed: int = _phantom.DEFAULT_SEED


@dataclass(frozen=True)
class Camera:
    """Initial camera in the case frame: eye and focal point [mm], up vector."""

    eye_mm: tuple[float, float, float]
    focal_mm: tuple[float, float, float]
    up: tuple[float, float, float]


@dataclass(frozen=True)
class Target:
    """The procedure's target.

    Attributes
    ----------
    description : str
        Free text (e.g. "cortical mastoidectomy").
    structures : tuple of str
        Structures the procedure should expose (identify under a thin plate or
        uncover) without injuring them.
    box_min_mm, box_max_mm : (3,) float or None
        Corners of the box the drilling is expected to stay in [mm].
    """

    description: str = ""
    structures: tuple[str, ...] = ()
    box_min_mm: tuple[float, float, float] | None = None
    box_max_mm: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Case:
    """A parsed case manifest.

    Attributes
    ----------
    name, description : str
    side : str
        ``"left"`` or ``"right"`` ear (for a left ear, lateral is ``+x``).
    manifest : Path
        The ``case.toml`` read.
    volume : VolumeSpec
    structures : tuple of Structure
        In label-index order (structure ``s`` has index ``s + 1``).
    camera : Camera
    target : Target or None
    """

    name: str
    description: str
    side: str
    manifest: Path
    volume: VolumeSpec
    structures: tuple[Structure, ...]
    camera: Camera
    target: Target | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """Structure names in index order."""
        return tuple(s.name for s in self.structures)

    def index(self, name: str) -> int:
        """1-based label index of structure ``name``."""
        try:
            return self.names.index(name) + 1
        except ValueError:
            raise KeyError(f"case {self.name!r} has no structure {name!r}; "
                           f"structures: {list(self.names)}") from None

    @property
    def bone_index(self) -> int:
        """Index of the first structure of kind ``"bone"``."""
        return next(i for i, s in enumerate(self.structures, start=1)
                    if s.kind == "bone")

    @property
    def lateral(self) -> np.ndarray:
        """Unit vector pointing laterally for this ear in the case frame."""
        return np.array([1.0 if self.side == "left" else -1.0, 0.0, 0.0])

    def load_volume(self) -> CaseVolume:
        """Read (or generate) the case's volume on its isotropic grid."""
        v = self.volume
        names = self.names
        if v.format == "phantom":
            size = v.size_mm if v.size_mm is not None else _phantom.DEFAULT_SIZE_MM
            return _phantom.phantom_volume(v.seed, v.voxel_mm, size, names)
        return load_volume(
            v.format, v.path, kinds=[s.kind for s in self.structures],
            label_values=[s.label for s in self.structures],
            colors=[s.color for s in self.structures], voxel_mm=v.voxel_mm,
            bone_threshold_hu=v.bone_threshold_hu, labels_path=v.labels,
            pattern=v.pattern, size_mm=v.size_mm, unknown_colors=v.unknown_colors,
            origin_mm=v.origin_mm)


# ------------------------------------------------------------------ parsing
def _rgb(table: dict, key: str, path: Path, where: str) -> tuple[int, int, int]:
    rgb = get_vector(table, key, path, where, length=3, integer=True)
    if any(c < 0 or c > 255 for c in rgb):
        raise BonesimError(f"'{key}' components must lie in 0-255, got {list(rgb)}",
                           path, where)
    return tuple(int(c) for c in rgb)


def _positive_vector(table, key, path, where) -> tuple[float, float, float]:
    vec = get_vector(table, key, path, where)
    if any(not math.isfinite(v) or v <= 0 for v in vec):
        raise BonesimError(f"'{key}' must be three positive numbers, got {list(vec)}",
                           path, where)
    return tuple(float(v) for v in vec)


def _relative(table, key, path: Path, where: str) -> Path | None:
    if key not in table:
        return None
    value = get_str(table, key, path, where)
    if not value.strip():
        raise BonesimError(f"'{key}' must not be empty", path, where)
    p = Path(value).expanduser()
    return p if p.is_absolute() else (path.parent / p)


def _parse_volume(tab, path: Path) -> VolumeSpec:
    where = "volume"
    if not isinstance(tab, dict):
        raise BonesimError("expected a [volume] table", path, where)
    fmt = get_str(tab, "format", path, where, choices=FORMATS)
    allowed = _VOLUME_COMMON + _VOLUME_KEYS[fmt]
    for key in tab:
        if key not in allowed and any(key in ks for ks in _VOLUME_KEYS.values()):
            raise BonesimError(f"key '{key}' does not apply to format '{fmt}'",
                               path, where)
    check_keys(tab, allowed, path, where)
    voxel = float(get_number(tab, "voxel_mm", path, where, default=DEFAULT_VOXEL_MM,
                             minimum=MIN_VOXEL_MM, maximum=MAX_VOXEL_MM))
    spec = dict(format=fmt, voxel_mm=voxel)
    if fmt == "phantom":
        spec["seed"] = int(get_number(tab, "seed", path, where,
                                      default=_phantom.DEFAULT_SEED, integer=True))
        if "size_mm" in tab:
            spec["size_mm"] = _positive_vector(tab, "size_mm", path, where)
        return VolumeSpec(**spec)
    spec["path"] = _relative(tab, "path", path, where)
    if fmt == "label-stack":
        if spec["path"] is None:
            raise BonesimError("missing required key 'path'", path, where)
        spec["pattern"] = get_str(tab, "pattern", path, where, default=DEFAULT_PATTERN)
        if "size_mm" not in tab:
            raise BonesimError("missing spacing: a label stack needs 'size_mm' = "
                               "[x, y, z], its physical extent", path, where)
        spec["size_mm"] = _positive_vector(tab, "size_mm", path, where)
        spec["unknown_colors"] = get_str(tab, "unknown_colors", path, where,
                                         default="error", choices=UNKNOWN_COLOR_MODES)
        if "origin_mm" in tab:
            spec["origin_mm"] = tuple(float(v) for v in
                                      get_vector(tab, "origin_mm", path, where))
        return VolumeSpec(**spec)
    thr = get_number(tab, "bone_threshold_hu", path, where,
                     default=DEFAULT_BONE_THRESHOLD_HU)
    if not math.isfinite(thr):
        raise BonesimError("'bone_threshold_hu' must be finite", path, where)
    spec["bone_threshold_hu"] = float(thr)
    spec["labels"] = _relative(tab, "labels", path, where)
    if spec["path"] is None and (fmt == "dicom" or spec["labels"] is None):
        raise BonesimError("missing required key 'path'" +
                           ("" if fmt == "dicom" else " (or 'labels')"), path, where)
    if spec["labels"] is not None and not spec["labels"].name.lower().endswith(
            (".nrrd", ".nhdr", ".nii", ".nii.gz")):
        raise BonesimError("'labels' must be a .nrrd / .nhdr / .nii / .nii.gz file, "
                           f"got {spec['labels'].name!r}", path, where)
    return VolumeSpec(**spec)


def _parse_structures(items, path: Path, fmt: str) -> tuple[Structure, ...]:
    if not isinstance(items, list) or not items:
        raise BonesimError("need at least one [[structures]] entry", path, "structures")
    if len(items) > MAX_STRUCTURES:
        raise BonesimError(f"at most {MAX_STRUCTURES} structures, got {len(items)}",
                           path, "structures")
    out, names, labels, colors = [], {}, {}, {}
    for i, tab in enumerate(items):
        where = f"structures[{i}]"
        check_keys(tab, _STRUCTURE_KEYS, path, where, required=("name", "kind"))
        name = get_str(tab, "name", path, where)
        if not name.strip():
            raise BonesimError("'name' must not be empty", path, where)
        if name in names:
            raise BonesimError(f"duplicate structure name {name!r} (also "
                               f"structures[{names[name]}])", path, where)
        names[name] = i
        kind = get_str(tab, "kind", path, where, choices=KINDS)
        label = None
        if "label" in tab:
            label = int(get_number(tab, "label", path, where, integer=True,
                                   minimum=1, maximum=MAX_LABEL))
            if label in labels:
                raise BonesimError(f"label {label} already used by "
                                   f"{labels[label]!r}", path, where)
            labels[label] = name
        color = None
        if "color" in tab:
            color = _rgb(tab, "color", path, where)
            if color == (0, 0, 0):
                raise BonesimError("'color' [0, 0, 0] is reserved for background",
                                   path, where)
            if color in colors:
                raise BonesimError(f"color {list(color)} already used by "
                                   f"{colors[color]!r}", path, where)
            colors[color] = name
        elif fmt == "label-stack":
            raise BonesimError("a label-stack structure needs 'color' = [r, g, b]",
                               path, where)
        if fmt == "phantom" and name not in _phantom.PARTS:
            raise BonesimError(f"unknown phantom part {name!r}; the phantom paints "
                               f"{list(_phantom.PARTS)}", path, where)
        display = (_rgb(tab, "display_color", path, where) if "display_color" in tab
                   else PALETTE[i % len(PALETTE)])
        monitor = tab.get("monitor", False)
        if not isinstance(monitor, bool):
            raise BonesimError(f"'monitor' must be true or false, got {monitor!r}",
                               path, where)
        if monitor and kind == "bone":
            raise BonesimError("'monitor' = true on a structure of kind 'bone'; the "
                               "nerve monitor watches nerves (kind 'critical' or "
                               "'soft')", path, where)
        out.append(Structure(name, kind, label, color, display, monitor))
    if not any(s.kind == "bone" for s in out):
        raise BonesimError("no structure of kind 'bone'; one is needed (intensity "
                           "volumes threshold into the first one)", path, "structures")
    return tuple(out)


def _parse_camera(tab, path: Path) -> Camera:
    where = "camera"
    check_keys(tab, _CAMERA_KEYS, path, where, required=_CAMERA_KEYS)
    eye, focal, up = (np.array(get_vector(tab, k, path, where), dtype=float)
                      for k in _CAMERA_KEYS)
    view = focal - eye
    if not np.all(np.isfinite(np.r_[eye, focal, up])):
        raise BonesimError("camera vectors must be finite", path, where)
    if np.linalg.norm(view) == 0:
        raise BonesimError("'eye_mm' and 'focal_mm' coincide", path, where)
    if np.linalg.norm(np.cross(view, up)) <= 1e-6 * np.linalg.norm(view) * max(
            np.linalg.norm(up), 1e-300):
        raise BonesimError("'up' is zero or parallel to the viewing direction",
                           path, where)
    return Camera(*(tuple(float(c) for c in v) for v in (eye, focal, up)))


def _parse_target(tab, path: Path, names) -> Target:
    where = "target"
    check_keys(tab, _TARGET_KEYS, path, where)
    desc = get_str(tab, "description", path, where, default="")
    structs = tab.get("structures", [])
    if not isinstance(structs, list) or not all(isinstance(s, str) for s in structs):
        raise BonesimError("'structures' must be a list of structure names",
                           path, where)
    unknown = [s for s in structs if s not in names]
    if unknown:
        raise BonesimError(f"unknown structure(s) {unknown}; structures: "
                           f"{list(names)}", path, where)
    lo = hi = None
    if "box_mm" in tab:
        box = tab["box_mm"]
        ok = (isinstance(box, list) and len(box) == 2
              and all(isinstance(c, list) and len(c) == 3 for c in box)
              and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                      for c in box for v in c))
        if not ok:
            raise BonesimError("'box_mm' must be [[xmin, ymin, zmin], [xmax, ymax, "
                               f"zmax]], got {box!r}", path, where)
        lo, hi = (tuple(float(v) for v in c) for c in box)
        if any(a >= b for a, b in zip(lo, hi)):
            raise BonesimError(f"'box_mm' min {list(lo)} must be below max {list(hi)} "
                               "on every axis", path, where)
    return Target(desc, tuple(structs), lo, hi)


def parse_case(path: str | Path) -> Case:
    """Parse and check one ``case.toml`` (no volume is read)."""
    path = Path(path).resolve()
    doc = read_toml(path)
    check_keys(doc, _TOP_KEYS, path, "top level",
               required=("case", "volume", "structures", "camera"))
    case = doc["case"]
    check_keys(case, _CASE_KEYS, path, "case", required=("name", "side"))
    name = get_str(case, "name", path, "case")
    if not name.strip():
        raise BonesimError("'name' must not be empty", path, "case")
    desc = get_str(case, "description", path, "case", default="")
    side = get_str(case, "side", path, "case", choices=SIDES)
    volume = _parse_volume(doc["volume"], path)
    structures = _parse_structures(doc["structures"], path, volume.format)
    camera = _parse_camera(doc["camera"], path)
    target = (_parse_target(doc["target"], path, [s.name for s in structures])
              if "target" in doc else None)
    return Case(name, desc, side, path, volume, structures, camera, target)


# ------------------------------------------------------------------ lookup
def cases_dir() -> Path:
    """Folder of the bundled cases (the ``ct_cases`` package)."""
    import ct_cases

    return Path(ct_cases.__file__).resolve().parent


def _bundled() -> dict[str, Path]:
    root = cases_dir()
    return {p.parent.name: p for p in sorted(root.glob(f"*/{CASE_FILE}"))}


def load_case(name_or_path: str | Path = "phantom") -> Case:
    """Load a bundled case by name, or any case by manifest or folder path.

    Parameters
    ----------
    name_or_path : str or Path
        A bundled case name (a folder of the ``ct_cases`` package, e.g.
        ``"phantom"``), or the path of a ``case.toml`` or of a folder holding
        one. A bare name that matches a bundled case wins over a same-named
        folder in the working directory.
    """
    text = str(name_or_path)
    bundled = _bundled()
    bare = isinstance(name_or_path, str) and "/" not in text and "\\" not in text \
        and not text.endswith(".toml")
    if bare and text in bundled:
        return parse_case(bundled[text])
    path = Path(name_or_path).expanduser()
    if path.is_dir():
        manifest = path / CASE_FILE
        if not manifest.is_file():
            raise BonesimError(f"folder has no {CASE_FILE}", path)
        return parse_case(manifest)
    if path.is_file():
        return parse_case(path)
    if bare:
        raise BonesimError(f"no bundled case named {text!r} and no such file or "
                           f"folder; bundled cases: {sorted(bundled)}", path)
    raise BonesimError("case manifest or folder not found", path)


def list_cases() -> list[Case]:
    """All bundled cases, sorted by folder name."""
    return [parse_case(p) for _, p in sorted(_bundled().items())]


def case_info(case: Case) -> dict:
    """Summary of a case and its loaded volume (for ``bonesim case-info``).

    Returns
    -------
    dict
        ``name, description, side, manifest, format, source, grid`` (nx, ny,
        nz), ``voxel_mm, origin_mm, extent_mm, counts`` (voxels per structure
        name), ``kinds`` (kind per structure name), ``monitored`` (names the
        nerve monitor watches), ``total`` (non-empty voxels).
    """
    vol = case.load_volume()
    counts = vol.counts(len(case.structures))
    return {
        "name": case.name,
        "description": case.description,
        "side": case.side,
        "manifest": str(case.manifest),
        "format": case.volume.format,
        "source": vol.source,
        "grid": list(vol.shape),
        "voxel_mm": vol.spacing_mm,
        "origin_mm": [float(v) for v in vol.origin_mm],
        "extent_mm": [float(v) for v in vol.extent_mm],
        "counts": {s.name: int(counts[i]) for i, s in enumerate(case.structures, 1)},
        "kinds": {s.name: s.kind for s in case.structures},
        "monitored": [s.name for s in case.structures if s.monitor],
        "total": int(counts[1:].sum()),
    }


# ------------------------------------------------------------------ export
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            raise ValueError("TOML export of a non-finite number")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)          # JSON string escapes are valid TOML
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_table(header: str, table: dict) -> str:
    lines = [header]
    lines += [f"{k} = {_toml_value(v)}" for k, v in table.items() if v is not None]
    return "\n".join(lines) + "\n"


def _export_labels(structures) -> list[int]:
    """Label-map integer per structure: its own, else the smallest free one."""
    used = {s.label for s in structures if s.label is not None}
    out, nxt = [], 1
    for s in structures:
        if s.label is not None:
            out.append(s.label)
            continue
        while nxt in used:
            nxt += 1
        used.add(nxt)
        out.append(nxt)
    return out


def _export_colors(structures) -> list[tuple[int, int, int]]:
    """Label-stack colour per structure: unique, non-black."""
    taken: set = set()
    out = []
    for s in structures:
        c = s.color or s.display_color
        if c in taken or c == (0, 0, 0):
            c = next(p for p in PALETTE + tuple((r, 255 - r, 128) for r in range(256))
                     if p not in taken and p != (0, 0, 0))
        taken.add(c)
        out.append(tuple(int(v) for v in c))
    return out


def export_case(case: Case, fmt: str, out_dir: str | Path,
                overwrite: bool = False) -> Path:
    """Write the case's volume in another format plus a ``case.toml``.

    The written case loads back to the same labels (same grid, same counts per
    structure).

    Parameters
    ----------
    case : Case
    fmt : {"dicom", "nrrd", "nifti", "label-stack"}
        ``dicom``: folder ``ct/`` of slices + ``labels.nrrd``; ``nrrd``:
        ``ct.nrrd`` + ``labels.nrrd``; ``nifti``: ``ct.nii.gz`` +
        ``labels.nii.gz``; ``label-stack``: ``planes/plane1.png ...`` with one
        RGB colour per structure. Intensity formats hold HU (synthesised from
        the structure kinds when the source has none); in voxels labelled empty
        the HU are kept below the bone threshold so the labels reload exactly.
    out_dir : str or Path
        Created if needed.
    overwrite : bool
        Replace an existing ``case.toml`` in ``out_dir``.

    Returns
    -------
    Path
        The written ``case.toml``.
    """
    if fmt not in EXPORT_FORMATS:
        raise BonesimError(f"cannot export to {fmt!r}; formats: {list(EXPORT_FORMATS)}")
    out = Path(out_dir)
    manifest = out / CASE_FILE
    if manifest.exists() and not overwrite:
        raise BonesimError("already exists (choose another folder or overwrite)",
                           manifest)
    vol = case.load_volume()
    out.mkdir(parents=True, exist_ok=True)
    structs = case.structures
    thr = case.volume.bone_threshold_hu
    label_ints = _export_labels(structs)
    volume: dict = {"format": fmt, "voxel_mm": vol.spacing_mm}
    if fmt == "label-stack":
        colors = _export_colors(structs)
        write_label_stack(out / "planes", vol.labels, colors)
        volume.update(path="planes", pattern="plane*.png",
                      size_mm=[float(v) for v in vol.extent_mm],
                      origin_mm=[float(v) for v in vol.origin_mm])
    else:
        colors = [None] * len(structs)
        if vol.hu is not None:
            hu = vol.hu.copy()
        else:
            lut = np.array([EMPTY_HU] + [EXPORT_HU_BY_KIND[s.kind] for s in structs],
                           dtype=np.float32)
            hu = lut[vol.labels]
        below = np.float32(math.floor(thr) - 1)
        hu[(vol.labels == 0) & (hu > below)] = below
        lut = np.zeros(len(structs) + 1, dtype=np.uint16)
        lut[1:] = label_ints
        lmap = lut[vol.labels]
        if max(label_ints) <= np.iinfo(np.uint8).max:
            lmap = lmap.astype(np.uint8)
        if fmt == "dicom":
            write_dicom_series(out / "ct", hu, vol.spacing_mm, vol.origin_mm,
                               f"bonesim {case.name}")
            write_nrrd(out / "labels.nrrd", lmap, vol.spacing_mm, vol.origin_mm)
            volume.update(path="ct", labels="labels.nrrd")
        elif fmt == "nrrd":
            write_nrrd(out / "ct.nrrd", np.rint(hu).astype(np.int16), vol.spacing_mm,
                       vol.origin_mm)
            write_nrrd(out / "labels.nrrd", lmap, vol.spacing_mm, vol.origin_mm)
            volume.update(path="ct.nrrd", labels="labels.nrrd")
        else:
            write_nifti(out / "ct.nii.gz", np.rint(hu).astype(np.int16),
                        vol.spacing_mm, vol.origin_mm)
            write_nifti(out / "labels.nii.gz", lmap, vol.spacing_mm, vol.origin_mm)
            volume.update(path="ct.nii.gz", labels="labels.nii.gz")
        volume["bone_threshold_hu"] = thr

    desc = case.description
    note = f"exported as {fmt} from {case.manifest}"
    parts = [f"# bonesim case, {note}\n",
             _toml_table("[case]", {"name": case.name,
                                    "description": desc or note,
                                    "side": case.side}),
             _toml_table("[volume]", volume)]
    for s, lab, col in zip(structs, label_ints, colors):
        parts.append(_toml_table("[[structures]]", {
            "name": s.name, "kind": s.kind,
            "label": None if fmt == "label-stack" else lab,
            "color": col, "display_color": list(s.display_color),
            "monitor": True if s.monitor else None}))
    cam = case.camera
    parts.append(_toml_table("[camera]", {"eye_mm": cam.eye_mm,
                                          "focal_mm": cam.focal_mm, "up": cam.up}))
    if case.target is not None:
        t = case.target
        box = None if t.box_min_mm is None else [list(t.box_min_mm), list(t.box_max_mm)]
        parts.append(_toml_table("[target]", {"description": t.description,
                                              "structures": list(t.structures),
                                              "box_mm": box}))
    manifest.write_text("\n".join(parts), encoding="utf-8")
    return manifest
