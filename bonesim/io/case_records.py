"""The records a case manifest becomes: :class:`Case` and its parts.

:class:`Structure`, :class:`VolumeSpec`, :class:`Camera`, :class:`Target` and
:class:`Case` (with its volume loading, its display colours settled for a
volume and its derived surgical view), and the manifest's constants. The
manifest's layout and the public entry points (:func:`bonesim.io.case.load_case`,
...) are in :mod:`bonesim.io.case`; parsing is :mod:`bonesim.io.case_manifest`,
exports :mod:`bonesim.io.case_export`. Both build on this module, never on
:mod:`bonesim.io.case`, so the three import in one direction.
"""
from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io import anatomy as _anatomy
from bonesim.io import phantom as _phantom
from bonesim.io.limits import bound, check_grid
from bonesim.io.orientation import PATIENT_FRAME
from bonesim.io.recent import Recent
from bonesim.io.segmentation import SEG_SUFFIX
from bonesim.io.volumes import FORMATS, NATIVE, CaseVolume, load_volume

__all__ = ["CASE_FILE", "SIDES", "KINDS", "SEG_FORMAT", "CASE_FORMATS", "DEFAULT_VOXEL_MM",
           "DEFAULT_BONE_THRESHOLD_HU", "DEFAULT_PATTERN", "MIN_VOXEL_MM", "MAX_VOXEL_MM",
           "MAX_LABEL", "NATIVE", "ORIENTATION_SOURCES", "check_voxel_mm", "Structure", "VolumeSpec", "Camera",
           "Target", "Case", "Fragments"]

CASE_FILE = "case.toml"
SIDES = ("left", "right")
KINDS = ("bone", "critical", "soft")
SEG_FORMAT = "seg-nrrd"
CASE_FORMATS = tuple(dict.fromkeys(FORMATS + (SEG_FORMAT,)))
"""Volume formats a manifest may name."""
DEFAULT_VOXEL_MM = 0.5
DEFAULT_BONE_THRESHOLD_HU = 300.0
DEFAULT_PATTERN = "*.png"
MIN_VOXEL_MM = bound("voxel_mm").min        # bonesim/data/limits.toml
MAX_VOXEL_MM = bound("voxel_mm").max
MAX_LABEL = 65535                     # label maps are at most 16-bit
ORIENTATION_SOURCES = ("declared", "file", "assumed", "generated")
"""How a case's orientation is known: declared in the manifest, read from the
file's header, assumed (a label stack without ``orientation``: LPS), or the
phantom's (generated in the patient frame)."""


def check_voxel_mm(value, path=None, where: str | None = None) -> float | str:
    """A ``voxel_mm`` as a manifest or ``--voxel-mm`` gives it: a number of mm
    in ``[MIN_VOXEL_MM, MAX_VOXEL_MM]`` or the string :data:`NATIVE`.

    Parameters
    ----------
    value : float, int or str
        The value given; on the command line (no ``path``) a string may hold
        a number.
    path, where : optional
        The manifest and its table, for the error (``case.toml [volume]:
        'voxel_mm' must be ...``); without them the value came from the
        command line and the error's field is ``--voxel-mm``.

    Returns
    -------
    float or "native"

    Raises
    ------
    BonesimError
        On anything else, in one line naming the manifest, table and key.
    """
    from bonesim.errors import BonesimError

    v = value
    if isinstance(v, str):
        text = v.strip()
        if text.lower() == NATIVE:
            return NATIVE
        try:
            v = float(text) if path is None else None
        except ValueError:
            v = None
    ok = (v is not None and not isinstance(v, bool) and isinstance(v, (int, float))
          and math.isfinite(v) and MIN_VOXEL_MM <= v <= MAX_VOXEL_MM)
    if not ok:
        msg = (f"must be a number of mm from {MIN_VOXEL_MM:g} to {MAX_VOXEL_MM:g} or "
               f"\"{NATIVE}\" (the source's own spacing), got {value!r}")
        if path is None:
            raise BonesimError(msg, field="--voxel-mm")
        raise BonesimError("'voxel_mm' " + msg, path, where)
    return float(v)


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
        The nerve monitor (:mod:`bonesim.runtime.monitor`) reports the simulated
        activity of this structure (nerves such as the facial nerve).
    color_source : str
        Where ``display_color`` came from (:data:`bonesim.io.anatomy.COLOR_SOURCES`):
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

    @property
    def display_name(self) -> str:
        """The name shown on screen (window, HUD, monitor trace, legends,
        pictures, the commands' text): :func:`bonesim.io.anatomy.clinical_name`
        of :attr:`name` (``facial_nerve`` -> ``Facial nerve``). Files keep
        :attr:`name`."""
        return _anatomy.clinical_name(self.name)

    @property
    def monitor_available(self) -> bool:
        """A nerve the monitor could watch (:attr:`monitor` says whether it
        does): its anatomical class is a nerve and its kind is not bone."""
        cls = _anatomy.load_table().classes.get(self.anatomy)
        return self.kind != "bone" and cls is not None and cls.nerve


@dataclass(frozen=True)
class VolumeSpec:
    """The ``[volume]`` table, paths resolved against the manifest's folder.

    Attributes
    ----------
    format : str
        One of :data:`CASE_FORMATS`, or ``"session"`` for a case a session
        file carries (:mod:`bonesim.io.embedded`; never in a manifest).
    path : Path or None
        Volume file / folder (None for the phantom and label-only cases).
    voxel_mm : float or "native"
        Isotropic voxel edge after loading [mm], or :data:`NATIVE`: the
        source's own spacing (its finest axis when anisotropic, see
        :func:`bonesim.io.volumes.engine_voxel_mm`; for the phantom, which has
        no source, the generator's default
        :data:`bonesim.io.phantom.DEFAULT_VOXEL_MM`).
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
    generation : int
        Phantom shape generation (:data:`bonesim.io.phantom.GENERATIONS`).
    """

    format: str
    path: Path | None = None
    voxel_mm: float | str = DEFAULT_VOXEL_MM
    bone_threshold_hu: float = DEFAULT_BONE_THRESHOLD_HU
    labels: Path | None = None
    pattern: str = DEFAULT_PATTERN
    size_mm: tuple[float, float, float] | None = None
    unknown_colors: str = "error"
    origin_mm: tuple[float, float, float] | None = None
    orientation: str | None = None
    seed: int = _phantom.DEFAULT_SEED
    generation: int = _phantom.LATEST_GENERATION

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
class Fragments:
    """How cut-off bone is handled (``[fragments]``; :mod:`bonesim.engine.fragments`).

    Attributes
    ----------
    speck_voxels : int
        Parts cut off with fewer voxels than this are removed as dust instead
        of becoming bodies (default
        :data:`bonesim.engine.fragments.DEFAULT_SPECK_VOXELS`).
    """

    # the engine's DEFAULT_SPECK_VOXELS, written out: importing the fragment
    # kernels here would load numba and scipy.ndimage with every case file
    # (tests/bonesim/io/test_case_physics.py checks the two agree)
    speck_voxels: int = 8


#: Phantom cases whose derived landmarks, frame check and view the process
#: keeps (:meth:`Case._derive`).
CACHED_DERIVED = 8
_DERIVED_KEYS = ("landmarks", "frame", "view")
_derived_cache = Recent(CACHED_DERIVED)


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
    fragments : Fragments
        The manifest's ``[fragments]`` (defaults without it).
    gravity : (3,) float or None
        The manifest's ``[physics] gravity`` direction, case frame (None:
        the camera's viewing direction, see :attr:`gravity_dir`).
    """

    name: str
    description: str
    side: str
    manifest: Path
    volume: VolumeSpec
    structures: tuple[Structure, ...]
    declared_camera: Camera | None = None
    target: Target | None = None
    fragments: Fragments = Fragments()
    gravity: tuple | None = None
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

    @property
    def gravity_dir(self) -> tuple:
        """Unit direction of gravity, case frame: the manifest's
        ``[physics] gravity``, else the initial camera's viewing direction
        (the surgeon looks down into the mastoid; the same choice as the
        bone dust's). Fragments and plates fall along it."""
        if self.gravity is not None:
            g = np.asarray(self.gravity, dtype=float)
        else:
            cam = self.camera
            g = np.asarray(cam.focal_mm, dtype=float) - np.asarray(cam.eye_mm, dtype=float)
        return tuple(float(v) for v in g / np.linalg.norm(g))

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
        """The derived :class:`~bonesim.io.surgical_view.SurgicalView` (with its
        landmarks and notes), computing it as :attr:`camera` does."""
        if "view" not in self._derived:
            self.load_volume()
        return self._derived["view"]

    @property
    def landmarks(self):
        """The :class:`~bonesim.io.landmarks.Landmarks` of the mastoidectomy,
        read from the volume (loaded once, then cached)."""
        if "landmarks" not in self._derived:
            self.load_volume()
        return self._derived["landmarks"]

    @property
    def frame_check(self):
        """How the anatomy agrees with the declared side and orientation
        (:class:`~bonesim.io.anatomy_frame.FrameCheck`)."""
        if "frame" not in self._derived:
            self.load_volume()
        return self._derived["frame"]

    def orientation_problem(self) -> str:
        """One line naming where the anatomy contradicts the declared side or
        orientation, with the code that fits it; empty when it agrees."""
        code, how = self.orientation
        return self.frame_check.message(code if how in ("declared", "assumed") else None,
                                        how, self.side)

    def require_orientation(self, accept: bool = False) -> str:
        """Refuse a case whose anatomy contradicts its declaration.

        Parameters
        ----------
        accept : bool
            Drill it as declared anyway (``--accept-orientation``).

        Returns
        -------
        str
            The contradiction when accepted (for a notice), else ``""``.

        Raises
        ------
        BonesimError
            Naming the manifest, the contradiction and the fitting code.
        """
        problem = self.orientation_problem()
        if problem and not accept:
            raise BonesimError(problem + "; --accept-orientation drills it as declared",
                               self.manifest)
        return problem

    def _derive(self, vol: CaseVolume) -> None:
        """Landmarks, frame check and (without ``[camera]``) the view of
        ``vol``; a phantom case's (its volume a function of the manifest)
        are found once per process (:data:`CACHED_DERIVED`), each case
        getting its own copy."""
        if self.volume.format != "phantom":
            self._derive_from(vol)
            return
        import copy

        done = _derived_cache.get(self)
        if done is None:
            self._derive_from(vol)
            _derived_cache.put(self, copy.deepcopy({k: self._derived[k] for k in _DERIVED_KEYS
                                                    if k in self._derived}))
        else:
            self._derived.update(copy.deepcopy(done))

    def _derive_from(self, vol: CaseVolume) -> None:
        from bonesim.io.anatomy_frame import check_frame
        from bonesim.io.landmarks import find_landmarks
        from bonesim.io.surgical_view import view_from_landmarks

        lm = find_landmarks(vol.labels, vol.spacing_mm, vol.origin_mm, self.structures,
                            self.side)
        code, how = self.orientation
        self._derived["landmarks"] = lm
        self._derived["frame"] = check_frame(
            lm.masks, lm.cortex["h"], lm.cortex["origin_mm"], self.side,
            code if how in ("declared", "assumed") else None)
        if self.declared_camera is None:
            self._derived["view"] = view_from_landmarks(lm)

    # ----------------------------------------------------------- volume
    def with_voxel_mm(self, voxel_mm: float | str) -> "Case":
        """This case with its engine voxel set to ``voxel_mm`` (``--voxel-mm``).

        Parameters
        ----------
        voxel_mm : float or "native"
            Isotropic voxel edge [mm] (checked as the manifest's key is, see
            :func:`check_voxel_mm`), or :data:`NATIVE`: the source's spacing.
            The phantom has no source: ``"native"`` keeps the voxel its
            manifest gives (the generator's default if that is ``"native"``
            too).

        Returns
        -------
        Case
            A new case (nothing derived from a volume is carried over).
        """
        v = check_voxel_mm(voxel_mm)
        if v == NATIVE and self.volume.format == "phantom":
            v = self.volume.voxel_mm
        return dataclasses.replace(self, volume=dataclasses.replace(self.volume, voxel_mm=v))

    def load_volume(self, progress=None) -> CaseVolume:
        """Read (or generate) the case's volume on its isotropic grid.

        Parameters
        ----------
        progress : callable, optional
            ``progress(done, total, what)`` while a big volume loads (passed
            to :func:`bonesim.io.volumes.load_volume`).

        The landmarks, the side and orientation check and (for a case
        without ``[camera]``) the surgical view are derived from this volume
        and cached, so :attr:`camera` and :attr:`landmarks` do not read it
        again.
        """
        v = self.volume
        names = self.names
        if v.format == "phantom":
            size = v.size_mm if v.size_mm is not None else _phantom.DEFAULT_SIZE_MM
            voxel = _phantom.DEFAULT_VOXEL_MM if v.voxel_mm == NATIVE else v.voxel_mm
            check_grid(size, voxel, self.manifest, "volume")   # before allocating it
            vol = _phantom.phantom_volume(v.seed, voxel, size, names, v.generation)
        elif v.format == "session":       # carried by a session file (bonesim.io.embedded)
            from bonesim.io.embedded import read_volume

            # the reader hands over what it read with the file open (once)
            vol = self._derived.pop("session_volume", None) or read_volume(v.path)
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
        if "landmarks" not in self._derived:
            self._derive(vol)
        return vol

    def hand_over(self, vol: CaseVolume) -> None:
        """Give a case carried by a session file (format ``"session"``) the
        volume its reader already read with the file open: the next
        :meth:`load_volume` takes it instead of opening the file again."""
        self._derived["session_volume"] = vol

    def neighbours(self, vol: CaseVolume) -> np.ndarray:
        """Which structures are neighbours for the display colours: within the
        anatomy table's ``neighbour_mm``, measured on ``vol``'s source labels
        (:attr:`~bonesim.io.volumes.CaseVolume.native_labels`) on the table's
        fixed ``analysis_mm`` lattice (:func:`bonesim.io.anatomy.case_neighbours`),
        so the same source gives the same neighbours at every ``voxel_mm``.
        Computed once per volume.

        Returns
        -------
        (n, n) bool
        """
        native = vol.native_labels
        got = self._derived.get("neighbours")
        if got is not None and got[0]() is native.labels:
            return got[1]
        adj = _anatomy.case_neighbours(native, len(self.structures))
        # a weak reference: the case must not keep a big label map alive
        self._derived["neighbours"] = (weakref.ref(native.labels), adj)
        return adj

    def resolved(self, vol: CaseVolume) -> "Case":
        """This case with display colours settled for ``vol``.

        Neighbouring structures (:meth:`neighbours`: within the anatomy
        table's ``neighbour_mm``, measured at a fixed resolution of the
        source, so the colours do not change with ``voxel_mm``) whose colours
        would look alike get other colours; only colours the manifest did not
        set change (see :func:`bonesim.io.anatomy.resolve_colors`). The
        surgical view is derived from ``vol`` too. ``vol`` must be this case's
        volume.
        """
        table = _anatomy.load_table()
        structs = list(self.structures)
        if any(s.color_source != "manifest" for s in structs):
            adj = self.neighbours(vol)
            cands = [_color_candidates(s, table) for s in structs]
            colors = _anatomy.resolve_colors([s.display_color for s in structs],
                                             [s.color_source for s in structs], cands,
                                             adj, table.min_delta_e)
            structs = [dataclasses.replace(s, display_color=c)
                       for s, c in zip(structs, colors)]
        out = dataclasses.replace(self, structures=tuple(structs))
        out._derived.update(self._derived)
        if "landmarks" not in out._derived:
            out._derive(vol)
            for k, v in out._derived.items():
                self._derived.setdefault(k, v)
        return out


def _color_candidates(s: Structure, table) -> list:
    cls = table.classes.get(s.anatomy)
    own = list(cls.colors) if cls is not None else []
    return own + list(table.kind_colors[s.kind]) + list(table.fallback)
