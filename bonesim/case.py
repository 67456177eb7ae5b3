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
    format = "nrrd"                   # phantom | dicom | nrrd | nifti |
                                      # label-stack | seg-nrrd
    path = "ct.nrrd"                  # relative to this manifest (not for phantom)
    voxel_mm = 0.5                    # isotropic output voxel edge, default 0.5
    bone_threshold_hu = 300           # dicom / nrrd / nifti, default 300
    labels = "labels.nrrd"            # dicom / nrrd / nifti: optional label map
                                      # (a .seg.nrrd alone makes a seg-nrrd case)
    # label-stack only:
    #   pattern = "*.png"  size_mm = [columns, rows, slices]
    #   orientation = "LPS"  (axis code; default LPS, "assumed")
    #   origin_mm = [x, y, z]  (LPS centre of the first slice's top-left pixel;
    #                           default centred)   unknown_colors = "error"
    # phantom only:
    #   seed = 0  size_mm = [52, 52, 52]

    [[structures]]                    # order = label index 1, 2, ...
    name = "bone"
    kind = "bone"                     # bone | critical | soft (seg-nrrd: optional)
    label = 1                         # label-map integer (intensity formats)
    color = [230, 220, 200]           # label-stack colour (label-stack: required)
    segment = "Bone"                  # seg-nrrd: segment name or ID (default: name)
    anatomy = "bone"                  # optional: class of bonesim/data/anatomy.toml
    display_color = [230, 220, 200]   # rendering colour (default: from the data)
    monitor = false                   # nerve monitor (default: true for nerves)

    [camera]                          # optional; case frame (LPS), mm
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
For a seg-nrrd case ``[[structures]]`` is optional: without it the
structures are the file's segments, with their names and colours and a kind
read from the name.

Defaults read from the anatomy (:mod:`bonesim.anatomy`, ``docs/cases.md``):
``display_color`` is the label stack's colour, the segment's colour, or a
conventional palette colour for the structure's name and kind, changed where
it would look like a neighbour's (:meth:`Case.resolved`); ``monitor`` is on
for structures whose name says nerve; without ``[camera]`` the camera is the
surgeon's lateral view of the mastoid (:mod:`bonesim.surgical_view`).

Every problem is raised as a :class:`~bonesim.errors.BonesimError` naming the
manifest and the offending key.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import anatomy as _anatomy
from . import phantom as _phantom
from .case_export import EXPORT_FORMATS, export_case
from .errors import BonesimError
from .orientation import PATIENT_FRAME
from .segmentation import SEG_SUFFIX
from .volumes import FORMATS, CaseVolume, load_volume

__all__ = ["CASE_FILE", "SIDES", "KINDS", "CASE_FORMATS", "EXPORT_FORMATS",
           "Structure", "VolumeSpec", "Camera", "Target", "Case", "parse_case",
           "cases_dir", "load_case", "list_cases", "case_info", "export_case"]

CASE_FILE = "case.toml"
SIDES = ("left", "right")
KINDS = ("bone", "critical", "soft")
SEG_FORMAT = "seg-nrrd"
CASE_FORMATS = tuple(dict.fromkeys(FORMATS + (SEG_FORMAT,)))
"""Volume formats a manifest may name."""
DEFAULT_VOXEL_MM = 0.5
DEFAULT_BONE_THRESHOLD_HU = 300.0
DEFAULT_PATTERN = "*.png"
MIN_VOXEL_MM = 0.01
MAX_VOXEL_MM = 10.0
MAX_LABEL = 65535                     # label maps are at most 16-bit
ORIENTATION_SOURCES = ("declared", "file", "assumed", "generated")
"""How a case's orientation is known: declared in the manifest, read from the
file's header, assumed (a label stack without ``orientation``: LPS), or the
phantom's (generated in the patient frame)."""

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
    color_source : str
        Where ``display_color`` came from (:data:`bonesim.anatomy.COLOR_SOURCES`):
        only ``"manifest"`` colours are never changed.
    anatomy : str
        Anatomical class (a class of ``bonesim/data/anatomy.toml``), ``""``
        when the name matches none.
    segment : str or None
        Segment (name or ID) of a 3D Slicer segmentation.
    """

    name: str
    kind: str
    label: int | None
    color: tuple[int, int, int] | None
    display_color: tuple[int, int, int]
    monitor: bool = False
    color_source: str = "manifest"
    anatomy: str = ""
    segment: str | None = None

    @property
    def role(self) -> str:
        """Landmark role of the anatomical class (``""`` for none)."""
        cls = _anatomy.load_table().classes.get(self.anatomy)
        return cls.role if cls is not None else ""


@dataclass(frozen=True)
class VolumeSpec:
    """The ``[volume]`` table, paths resolved against the manifest's folder.

    Attributes
    ----------
    format : str
        One of :data:`CASE_FORMATS`.
    path : Path or None
        Volume file / folder (None for the phantom and label-only cases).
    voxel_mm : float
        Isotropic voxel edge after loading [mm].
    bone_threshold_hu : float
        Bone threshold of intensity formats [HU].
    labels : Path or None
        Label map (NRRD / NIfTI, or a Slicer ``.seg.nrrd`` next to a CT).
    pattern : str
        Label-stack glob.
    size_mm : (3,) float or None
        Label-stack extent along image columns, rows and slices, or phantom
        extent ``(x, y, z)`` [mm].
    unknown_colors : str
        Label-stack policy for stray colours.
    origin_mm : (3,) float or None
        Label-stack: case-frame centre of the first slice's top-left pixel [mm].
    orientation : str or None
        Label-stack axis code as declared (None: not declared, read as LPS).
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
    orientation: str | None = None
    seed: int = _phantom.DEFAULT_SEED

    @property
    def segmentation(self) -> Path | None:
        """The Slicer segmentation the structures come from, if any."""
        if self.format == SEG_FORMAT:
            return self.path
        if self.labels is not None and self.labels.name.lower().endswith(SEG_SUFFIX):
            return self.labels
        return None


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
    declared_camera : Camera or None
        The manifest's ``[camera]`` (None: derived from the anatomy, see
        :attr:`camera`).
    target : Target or None
    """

    name: str
    description: str
    side: str
    manifest: Path
    volume: VolumeSpec
    structures: tuple[Structure, ...]
    declared_camera: Camera | None = None
    target: Target | None = None
    # what was derived from the volume (the surgical view); not part of the
    # manifest's identity, never passed in
    _derived: dict = field(default_factory=dict, init=False, compare=False, repr=False,
                           hash=False)

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

    @property
    def orientation(self) -> tuple[str | None, str]:
        """``(code, source)``: the volume's axis code and how it is known
        (:data:`ORIENTATION_SOURCES`; the code is None when the file holds it)."""
        v = self.volume
        if v.format == "phantom":
            return PATIENT_FRAME, "generated"
        if v.format == "label-stack":
            return (v.orientation, "declared") if v.orientation else \
                (PATIENT_FRAME, "assumed")
        return None, "file"

    # ----------------------------------------------------------- camera
    @property
    def camera_source(self) -> str:
        """``"manifest"`` (a ``[camera]`` table) or ``"anatomy"`` (derived)."""
        return "manifest" if self.declared_camera is not None else "anatomy"

    @property
    def camera(self) -> Camera:
        """The initial camera: the manifest's, else the surgeon's lateral view
        of the mastoid derived from the volume (loaded once if no volume was
        loaded through this case yet, then cached)."""
        if self.declared_camera is not None:
            return self.declared_camera
        if "view" not in self._derived:
            self.load_volume()
        view = self._derived["view"]
        return Camera(view.eye_mm, view.focal_mm, view.up)

    @property
    def surgical_view(self):
        """The derived :class:`~bonesim.surgical_view.SurgicalView` (with its
        landmarks and notes), computing it as :attr:`camera` does."""
        if "view" not in self._derived:
            self.load_volume()
        return self._derived["view"]

    def _derive_view(self, vol: CaseVolume) -> None:
        from .surgical_view import surgical_view

        self._derived["view"] = surgical_view(
            vol.labels, vol.spacing_mm, vol.origin_mm, [s.kind for s in self.structures],
            [s.role for s in self.structures], self.side, self.names)

    # ----------------------------------------------------------- volume
    def load_volume(self, progress=None) -> CaseVolume:
        """Read (or generate) the case's volume on its isotropic grid.

        Parameters
        ----------
        progress : callable, optional
            ``progress(done, total, what)`` while a big volume loads (passed
            to :func:`bonesim.volumes.load_volume`).

        The surgical view of a case without ``[camera]`` is derived from this
        volume and cached, so :attr:`camera` does not read it again.
        """
        v = self.volume
        names = self.names
        if v.format == "phantom":
            size = v.size_mm if v.size_mm is not None else _phantom.DEFAULT_SIZE_MM
            vol = _phantom.phantom_volume(v.seed, v.voxel_mm, size, names)
        else:
            kw = {"progress": progress}
            kinds = [s.kind for s in self.structures]
            if v.segmentation is not None:
                kw["segment_names"] = [s.segment for s in self.structures]
            if v.format == SEG_FORMAT:
                vol = load_volume(SEG_FORMAT, v.path, kinds=kinds, voxel_mm=v.voxel_mm,
                                  **kw)
            else:
                if v.format == "label-stack":
                    kw["orientation"] = v.orientation or PATIENT_FRAME
                vol = load_volume(
                    v.format, v.path, kinds=kinds,
                    label_values=[s.label for s in self.structures],
                    colors=[s.color for s in self.structures], voxel_mm=v.voxel_mm,
                    bone_threshold_hu=v.bone_threshold_hu, labels_path=v.labels,
                    pattern=v.pattern, size_mm=v.size_mm,
                    unknown_colors=v.unknown_colors, origin_mm=v.origin_mm, **kw)
        if self.declared_camera is None and "view" not in self._derived:
            self._derive_view(vol)
        return vol

    def resolved(self, vol: CaseVolume) -> "Case":
        """This case with display colours settled for ``vol``.

        Neighbouring structures (within the anatomy table's ``neighbour_mm``
        in ``vol``) whose colours would look alike get other colours; only
        colours the manifest did not set change (see
        :func:`bonesim.anatomy.resolve_colors`). The surgical view is derived
        from ``vol`` too. ``vol`` must be this case's volume.
        """
        table = _anatomy.load_table()
        structs = list(self.structures)
        if any(s.color_source != "manifest" for s in structs):
            adj = _anatomy.neighbours(vol.labels, len(structs), vol.spacing_mm,
                                      table.neighbour_mm)
            cands = [_color_candidates(s, table) for s in structs]
            colors = _anatomy.resolve_colors([s.display_color for s in structs],
                                             [s.color_source for s in structs], cands,
                                             adj, table.min_delta_e)
            structs = [dataclasses.replace(s, display_color=c)
                       for s, c in zip(structs, colors)]
        out = dataclasses.replace(self, structures=tuple(structs))
        out._derived.update(self._derived)
        if out.declared_camera is None:
            if "view" not in out._derived:
                out._derive_view(vol)
            self._derived.setdefault("view", out._derived["view"])
        return out


def _color_candidates(s: Structure, table) -> list:
    cls = table.classes.get(s.anatomy)
    own = list(cls.colors) if cls is not None else []
    return own + list(table.kind_colors[s.kind]) + list(table.fallback)


def parse_case(path: str | Path) -> Case:
    """Parse and check one ``case.toml`` (no volume is read; a segmentation's
    header is, for its segment table). See :mod:`bonesim.case_manifest`."""
    from .case_manifest import parse_manifest

    return parse_manifest(path)


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


def _color_warnings(case: Case, vol: CaseVolume) -> list[str]:
    """Neighbours whose manifest colours look alike (never changed)."""
    table = _anatomy.load_table()
    fixed = [i for i, s in enumerate(case.structures) if s.color_source == "manifest"]
    if len(fixed) < 2:
        return []
    adj = _anatomy.neighbours(vol.labels, len(case.structures), vol.spacing_mm,
                              table.neighbour_mm)
    out = []
    for a in fixed:
        for b in fixed:
            if a < b and adj[a, b]:
                sa, sb = case.structures[a], case.structures[b]
                d = float(_anatomy.delta_e(sa.display_color, sb.display_color))
                if d < table.warn_delta_e:
                    out.append(f"neighbours {sa.name!r} and {sb.name!r} have near-"
                               f"identical display colours {list(sa.display_color)} "
                               f"and {list(sb.display_color)} (CIEDE2000 difference "
                               f"{d:.0f}); both set in the manifest, so kept")
    return out


def case_info(case: Case, progress=None) -> dict:
    """Summary of a case and its loaded volume (for ``bonesim case-info``).

    Parameters
    ----------
    case : Case
    progress : callable, optional
        ``progress(done, total, what)`` while the volume loads.

    Returns
    -------
    dict
        ``name, description, side, manifest, format, source, frame``
        (the patient frame's name and axes), ``orientation`` (``code`` or
        None, ``source``), ``grid`` (nx, ny, nz), ``voxel_mm, origin_mm,
        extent_mm, counts`` (voxels per structure name), ``kinds`` (kind per
        structure name), ``colors`` (per name: ``rgb``, ``source``),
        ``monitored`` (names the nerve monitor watches), ``camera``
        (``eye_mm, focal_mm, up, source`` and, when derived, ``notes``),
        ``warnings`` (layout against the declared side, look-alike colours),
        ``total`` (non-empty voxels).
    """
    from .surgical_view import side_warnings

    vol = case.load_volume(progress=progress)
    rc = case.resolved(vol)
    counts = vol.counts(len(case.structures))
    cam = rc.camera
    camera = {"eye_mm": [round(c, 3) for c in cam.eye_mm],
              "focal_mm": [round(c, 3) for c in cam.focal_mm],
              "up": [round(c, 4) for c in cam.up], "source": rc.camera_source}
    if rc.declared_camera is None:
        camera["notes"] = list(rc.surgical_view.notes)
    code, how = case.orientation
    warnings = side_warnings(vol.labels, vol.spacing_mm, vol.origin_mm,
                             [s.kind for s in rc.structures],
                             [s.role for s in rc.structures], case.side, case.names)
    warnings += _color_warnings(rc, vol)
    return {
        "name": case.name,
        "description": case.description,
        "side": case.side,
        "manifest": str(case.manifest),
        "format": case.volume.format,
        "source": vol.source,
        "frame": {"name": PATIENT_FRAME, "x": "patient left", "y": "posterior",
                  "z": "superior", "units": "mm"},
        "orientation": {"code": code, "source": how},
        "grid": list(vol.shape),
        "voxel_mm": vol.spacing_mm,
        "origin_mm": [float(v) for v in vol.origin_mm],
        "extent_mm": [float(v) for v in vol.extent_mm],
        "counts": {s.name: int(counts[i]) for i, s in enumerate(case.structures, 1)},
        "kinds": {s.name: s.kind for s in case.structures},
        "colors": {s.name: {"rgb": list(s.display_color), "source": s.color_source}
                   for s in rc.structures},
        "monitored": [s.name for s in case.structures if s.monitor],
        "camera": camera,
        "warnings": warnings,
        "total": int(counts[1:].sum()),
    }
