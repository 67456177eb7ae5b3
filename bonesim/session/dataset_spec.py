"""What a vision dataset of a recorded run holds: its options, its class ids,
its provenance.

A dataset (``bonesim dataset RUN.h5 --out frames.h5``) is rendered from a
recording by :mod:`bonesim.render.dataset`; the file layout is
``docs/dataset_format.md``. This module holds everything about it that does
not draw (no VTK): the options and their checks (:class:`DatasetOptions`),
the segmentation's class ids (:func:`class_table`) and the provenance record
(:func:`provenance`). A dataset is a pure function of the recording and
the options: the provenance names both (the run file by its SHA-256, not by
its path) and nothing else, so that the same command gives the same bytes.

Segmentation classes
--------------------
``class`` (uint8, per pixel) names what the ray through the pixel's centre
meets first:

===========  =================================================================
id           meaning
===========  =================================================================
0            background (nothing drawn)
1 .. 199     the case's structure of that label (``header.structures``; the
             bone is a structure of kind ``bone``): the structure of the
             voxel the ray reaches on drawn tissue (a bone surface, or a
             structure's own mesh)
200          the burr (its sphere)
201          the drill's shaft
202          the suction tool
210          bone dust (a sprite's core, see :data:`SPRITE_LABEL_OPACITY`)
211          irrigation water (likewise)
220          a plate or distractor
255          anything else drawn (none today; a new kind of object would show
             here until it gets an id)
===========  =================================================================

``instance`` (int16) tells pieces apart: on tissue (structure ids on a bone
surface) the body the pixel shows (0 the main bone, ``k >= 1`` fragment
``k``: the ``body`` of the session's tissue events); on a plate its slot
(the ``body`` of its ``plate`` events); -1 everywhere else.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from bonesim.errors import BonesimError

__all__ = ["FORMAT", "VERSION", "CLASS_BACKGROUND", "MAX_STRUCTURE_ID", "CLASS_BURR",
           "CLASS_SHAFT", "CLASS_SUCTION", "CLASS_DUST", "CLASS_WATER", "CLASS_PLATE",
           "CLASS_OTHER", "NO_INSTANCE", "SPRITE_LABEL_OPACITY", "CAMERA_MODES",
           "SUCTION_MODES", "DEFAULT_SIZE", "DEFAULT_FPS", "ORBIT_HALF_ANGLE_DEG",
           "ORBIT_PERIOD_S", "DatasetOptions", "class_table", "file_sha256", "provenance",
           "to_json"]

#: Root attribute ``format`` of a dataset file.
FORMAT = "bonesim-dataset"
#: Layout version (``docs/dataset_format.md``).
VERSION = 1

CLASS_BACKGROUND = 0
#: Structure ids run 1 .. this (a case has at most this many structures).
MAX_STRUCTURE_ID = 199
CLASS_BURR = 200
CLASS_SHAFT = 201
CLASS_SUCTION = 202
CLASS_DUST = 210
CLASS_WATER = 211
CLASS_PLATE = 220
CLASS_OTHER = 255
#: ``instance`` where the pixel shows no body or plate.
NO_INSTANCE = -1
#: A dust or water sprite labels a pixel (and gives its depth) where its own
#: opacity there, ``alpha * (1 - r^2)^2`` (:mod:`bonesim.render.dustview`), is
#: at least this: its core. Fainter veils of dust leave the bone behind them
#: as the pixel's label.
SPRITE_LABEL_OPACITY = 0.15

CAMERA_MODES = ("recorded", "fixed", "orbit")
SUCTION_MODES = ("follow", "off")
DEFAULT_SIZE = (640, 480)
DEFAULT_FPS = 10.0
#: ``--camera orbit``: the eye circles the case camera's viewing axis on a
#: cone of this half-angle about the focal point [deg] ...
ORBIT_HALF_ANGLE_DEG = 25.0
#: ... once every this many seconds of the recording [s].
ORBIT_PERIOD_S = 12.0

#: id, name, kind and preview colour of the classes that are not structures.
_FIXED_CLASSES = (
    (CLASS_BURR, "burr", "tool", (255, 200, 40)), (CLASS_SHAFT, "shaft", "tool", (150, 150, 160)),
    (CLASS_SUCTION, "suction", "tool", (60, 140, 255)),
    (CLASS_DUST, "dust", "debris", (240, 110, 40)),
    (CLASS_WATER, "water", "fluid", (0, 220, 255)),
    (CLASS_PLATE, "plate", "implant", (200, 120, 255)),
    (CLASS_OTHER, "other", "other", (255, 0, 255)))


@dataclass(frozen=True)
class DatasetOptions:
    """How to render a dataset (the command's options; see ``bonesim dataset
    --help``).

    Attributes
    ----------
    rgb, depth, seg, normals, points : bool
        Streams to write. ``seg`` writes ``class`` and ``instance``;
        ``points`` the point clouds in the camera and the case frame.
    stereo_mm : float or None
        Baseline of a parallel stereo pair [mm] (None: one camera).
    camera : {"recorded", "fixed", "orbit"}
        ``recorded``: the recorded camera stream (the case camera where the
        file has none); ``fixed``: the case camera; ``orbit``: the case
        camera circling its axis (:data:`ORBIT_HALF_ANGLE_DEG`,
        :data:`ORBIT_PERIOD_S`).
    size : (int, int)
        Width, height [px].
    fps : float
        Frames per second of recording time [Hz].
    start, end : float or None
        Part of the recording [s of playback time] (default: all of it).
    hud : bool
        RGB with the window's HUD drawn over the view and the hidden burr's
        silhouette (labels and depth never see either).
    suction : {"follow", "off"}
        The recording holds no suction-tip pose. ``follow``: the other hand's
        suction-irrigator is drawn as the headless main job draws it (its
        tip trails the burr along its path by 0.5 s while the drill runs;
        water lands at the burr meanwhile), and it takes up dust and water;
        ``off``: no suction tool, water only where the recording's key
        events turned irrigation on.
    zoom : float
        The camera moves this many times closer to its focal point (1: as
        recorded).
    """

    rgb: bool = True
    depth: bool = True
    seg: bool = True
    normals: bool = False
    points: bool = False
    stereo_mm: float | None = None
    camera: str = "recorded"
    size: tuple = DEFAULT_SIZE
    fps: float = DEFAULT_FPS
    start: float | None = None
    end: float | None = None
    hud: bool = False
    suction: str = "follow"
    zoom: float = 1.0

    def __post_init__(self):
        if self.camera not in CAMERA_MODES:
            raise BonesimError(f"camera {self.camera!r} is not one of {list(CAMERA_MODES)}",
                               field="--camera")
        if self.suction not in SUCTION_MODES:
            raise BonesimError(f"suction {self.suction!r} is not one of "
                               f"{list(SUCTION_MODES)}", field="--suction")
        w, h = (int(v) for v in self.size)
        if not (16 <= w <= 8192 and 16 <= h <= 8192):
            raise BonesimError(f"size {w}x{h} must be 16..8192 pixels each way",
                               field="--size")
        object.__setattr__(self, "size", (w, h))
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise BonesimError(f"frame rate must be positive, got {self.fps}", field="--fps")
        if self.stereo_mm is not None and not (math.isfinite(self.stereo_mm)
                                               and self.stereo_mm > 0):
            raise BonesimError(f"stereo baseline must be a positive number of mm, got "
                               f"{self.stereo_mm}", field="--stereo")
        if not (math.isfinite(self.zoom) and self.zoom > 0):
            raise BonesimError(f"zoom must be positive, got {self.zoom}", field="--zoom")
        if not (self.rgb or self.depth or self.seg or self.normals or self.points):
            raise BonesimError("nothing to write: ask for at least one of --rgb, --depth, "
                               "--seg, --normals, --points")

    @property
    def eyes(self) -> tuple:
        """``("left",)`` or ``("left", "right")``."""
        return ("left",) if self.stereo_mm is None else ("left", "right")

    @property
    def needs_labels(self) -> bool:
        """Whether the label pass (depth, ids) must run."""
        return self.depth or self.seg or self.normals or self.points

    def to_dict(self) -> dict:
        """JSON-ready (stored in every dataset)."""
        d = asdict(self)
        d["size"] = list(self.size)
        return d


def class_table(structures) -> list[dict]:
    """The segmentation's classes: ``{"id", "name", "kind", "shown_as", "rgb"}``
    per id (``rgb``: a colour for previews, the structure's display colour).

    Parameters
    ----------
    structures : sequence
        The case's structures in label order (``name``, ``kind``; label
        ``s`` is ``structures[s - 1]``), e.g. ``model.structures``.
    """
    from bonesim.io.anatomy import clinical_name

    if len(structures) > MAX_STRUCTURE_ID:
        raise BonesimError(f"the case has {len(structures)} structures; datasets label "
                           f"at most {MAX_STRUCTURE_ID}")
    out = [{"id": CLASS_BACKGROUND, "name": "background", "kind": "background",
            "shown_as": "Background", "rgb": [0, 0, 0]}]
    for s, st in enumerate(structures, start=1):
        rgb = getattr(st, "display_color", None) or (200, 200, 200)
        out.append({"id": s, "name": str(st.name), "kind": str(st.kind),
                    "shown_as": clinical_name(str(st.name)),
                    "rgb": [int(v) for v in tuple(rgb)[:3]]})
    for cid, name, kind, rgb in _FIXED_CLASSES:
        out.append({"id": cid, "name": name, "kind": kind, "shown_as": name.capitalize(),
                    "rgb": list(rgb)})
    return out


def file_sha256(path, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


@dataclass(frozen=True)
class _Prov:
    bonesim_version: str
    run_sha256: str
    run_name: str
    case: dict
    options: dict
    frames: int
    schema: int = VERSION
    notes: list = field(default_factory=list)


def provenance(session, options: DatasetOptions, frames: int, notes=()) -> dict:
    """Where a dataset came from: the bonesim version, the run (its file's
    SHA-256 and name, its case as the header names it), the options, the
    frame count and notes (e.g. an incomplete recording). No time, host or
    path: the same command gives the same record.

    Parameters
    ----------
    session : Session
        As read by :func:`bonesim.session.reader.read_session` (``path``,
        ``header``).
    options : DatasetOptions
    frames : int
    notes : sequence of str
    """
    from bonesim import __version__

    path = getattr(session, "path", None)
    sha = file_sha256(path) if path is not None and Path(path).is_file() else ""
    case = dict((getattr(session, "header", None) or {}).get("case") or {})
    case.pop("path", None)                 # a path differs between machines
    return asdict(_Prov(__version__, sha, "" if path is None else Path(path).name,
                        case, options.to_dict(), int(frames), VERSION, list(notes)))


def to_json(obj) -> str:
    """Compact, key-sorted JSON (stable bytes for the same content)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))
