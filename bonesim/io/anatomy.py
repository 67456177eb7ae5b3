"""What a structure's name says: its anatomical class, default kind, colour and
nerve-monitor flag, and display colours that keep neighbours apart.

The table lives in ``bonesim/data/anatomy.toml`` (its header explains the
matching rules); :func:`classify` reads a structure name against it:
``"Facial_Nerve"``, ``"n. VII"``, ``"CN7"`` and ``"facial"`` all read as the
facial nerve, ``"ICA"`` as the carotid artery, ``"sinus tympani"`` as middle
ear (not the sigmoid sinus). A case uses the class for

* the **kind** of a structure a 3D Slicer segmentation brings without one,
* whether the **nerve monitor** watches it by default (a mastoidectomy's:
  the facial nerve and the chorda tympani) or could (the other nerves:
  vestibular, cochlear, any name saying "nerve"),
* its **clinical name** on screen (:func:`clinical_name`: ``facial_nerve``
  reads ``Facial nerve``, ``CN7`` reads ``Facial nerve``), while files keep
  the manifest's name,
* its **default display colour** (a conventional anatomical palette: nerves
  yellow, sinus and veins blue, arteries red, dura and tegmen pink-grey,
  labyrinth purple, ossicles teal, bone ivory), and
* the **landmarks** the automatic surgical view reads
  (:mod:`bonesim.io.surgical_view`).

Colours of neighbouring structures are then kept apart (:func:`neighbours`,
:func:`resolve_colors`): two structures within ``neighbour_mm`` of each other
must differ by ``min_delta_e`` (CIEDE2000); only colours the manifest did not
set are changed. Neighbours are measured on the source's labels pooled onto a
fixed ``analysis_mm`` lattice of the case frame, never on the engine's grid,
so a structure keeps its colour whatever ``voxel_mm`` the case is loaded at.
"""
from __future__ import annotations

import functools
import math
import re
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, get_str, read_toml

__all__ = ["ROLES", "COLOR_SOURCES", "AnatomyClass", "AnatomyTable", "default_table_path",
           "load_table", "normalize_name", "classify", "clinical_name", "default_kind",
           "default_monitor", "monitor_available", "default_color", "neighbours",
           "case_neighbours", "delta_e", "resolve_colors"]

#: Landmark roles a class may play for the surgical view.
ROLES = ("bone", "ear_canal", "middle_ear", "ossicles", "labyrinth", "sinus", "tegmen",
         "facial_nerve")

#: Where a structure's display colour came from, strongest first: set in the
#: manifest, the label stack's colour, the segmentation's segment colour, the
#: anatomical palette.
COLOR_SOURCES = ("manifest", "label", "segment", "palette")

_KINDS = ("bone", "critical", "soft")
_CLASS_KEYS = ("title", "kind", "nerve", "monitor", "colors", "names", "role")
_TOP_KEYS = ("colors", "kinds", "aliases", "classes", "view")
_ROMAN = {"i": "1", "ii": "2", "iii": "3", "iv": "4", "v": "5", "vi": "6", "vii": "7",
          "viii": "8", "ix": "9", "x": "10", "xi": "11", "xii": "12"}
_ORDINAL = ("st", "nd", "rd", "th")


# ---------------------------------------------------------------- the table
@dataclass(frozen=True)
class AnatomyClass:
    """One anatomical class of the table.

    Attributes
    ----------
    id : str
        Table key (``"facial_nerve"``).
    kind : str
        Default kind: ``"bone"``, ``"critical"`` or ``"soft"``.
    monitor : bool
        Watched by the nerve monitor by default.
    colors : tuple of (3,) int
        Display colours, conventional first, then alternates (RGB 0-255).
    names : tuple of tuple of str
        Normalised phrases (word tuples) that identify the class.
    role : str
        Landmark role for the surgical view (one of :data:`ROLES`) or ``""``.
    title : str
        Clinical name (``"Facial nerve"``).
    nerve : bool
        A nerve: the nerve monitor can watch it (on by default only where
        ``monitor``).
    """

    id: str
    kind: str
    monitor: bool
    colors: tuple
    names: tuple
    role: str = ""
    title: str = ""
    nerve: bool = False


@dataclass(frozen=True)
class AnatomyTable:
    """The parsed ``anatomy.toml``.

    Attributes
    ----------
    classes : dict of str -> AnatomyClass
        In file order (ties in matching go to the earlier class).
    aliases : dict of str -> tuple of str
        Word rewrites applied while normalising.
    kind_colors : dict of str -> tuple of (3,) int
        Colours of unmatched names, by kind.
    fallback : tuple of (3,) int
        Colours tried after a class's own.
    neighbour_mm : float
        Neighbour distance [mm].
    min_delta_e : float
        Least CIEDE2000 difference between neighbours' colours.
    warn_delta_e : float
        Manifest colours of neighbours closer than this are reported.
    view : dict of str -> float
        Surgical-view parameters (see :mod:`bonesim.io.surgical_view`).
    path : Path
        The file read.
    analysis_mm : float
        Cell edge of the fixed lattice neighbours are measured on [mm].
    """

    classes: dict
    aliases: dict
    kind_colors: dict
    fallback: tuple
    neighbour_mm: float
    min_delta_e: float
    warn_delta_e: float
    view: dict
    path: Path
    analysis_mm: float = 0.5


def default_table_path() -> Path:
    """The shipped ``bonesim/data/anatomy.toml``."""
    from bonesim.resources import data_path

    return data_path("anatomy.toml")


def _colors(value, path: Path, where: str) -> tuple:
    ok = (isinstance(value, list) and value and all(
        isinstance(c, list) and len(c) == 3 and all(
            isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in c)
        for c in value))
    if not ok:
        raise BonesimError(f"'colors' must be a non-empty list of [r, g, b] with "
                           f"components in 0-255, got {value!r}", path, where)
    return tuple(tuple(c) for c in value)


def _words(text: str, aliases: dict) -> tuple[str, ...]:
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    text = re.sub(r"(?<=[a-z])(?=[A-Z])", " ", text).lower()
    text = re.sub(r"(?<=[a-z])(?=[0-9])|(?<=[0-9])(?=[a-z])", " ", text)
    raw = re.sub(r"[^a-z0-9]+", " ", text).split()
    out: list[str] = []
    for w in raw:
        if w in _ORDINAL and out and out[-1].isdigit():
            continue
        if out and out[-1] == "nerve" and w in _ROMAN:
            out.append(_ROMAN[w])
            continue
        out.extend(aliases.get(w, (w,)))
    return tuple(out)


@functools.lru_cache(maxsize=4)
def _load_table(path: str) -> AnatomyTable:
    p = Path(path)
    doc = read_toml(p)
    check_keys(doc, _TOP_KEYS, p, "top level", required=_TOP_KEYS)
    ctab = doc["colors"]
    ckeys = ("neighbour_mm", "analysis_mm", "min_delta_e", "warn_delta_e", "fallback")
    check_keys(ctab, ckeys, p, "colors", required=ckeys)
    neighbour = float(get_number(ctab, "neighbour_mm", p, "colors", minimum=0.0,
                                 maximum=50.0))
    analysis = float(get_number(ctab, "analysis_mm", p, "colors", minimum=0.05,
                                maximum=10.0))
    min_de = float(get_number(ctab, "min_delta_e", p, "colors", minimum=0.0,
                              maximum=100.0))
    warn_de = float(get_number(ctab, "warn_delta_e", p, "colors", minimum=0.0,
                               maximum=100.0))
    fallback = _colors(ctab["fallback"], p, "colors")
    check_keys(doc["kinds"], _KINDS, p, "kinds", required=_KINDS)
    kind_colors = {k: _colors(doc["kinds"][k], p, f"kinds.{k}") for k in _KINDS}
    aliases = {}
    for k, v in doc["aliases"].items():
        if not isinstance(v, str) or not v.strip():
            raise BonesimError(f"alias {k!r} must be a non-empty string, got {v!r}",
                               p, "aliases")
        aliases[k.lower()] = tuple(v.lower().split())
    classes = {}
    for cid, tab in doc["classes"].items():
        where = f"classes.{cid}"
        check_keys(tab, _CLASS_KEYS, p, where, required=("kind", "colors", "names"))
        kind = get_str(tab, "kind", p, where, choices=_KINDS)
        flags = {}
        for key in ("monitor", "nerve"):
            flags[key] = tab.get(key, False)
            if not isinstance(flags[key], bool):
                raise BonesimError(f"'{key}' must be true or false, got {flags[key]!r}",
                                   p, where)
        title = get_str(tab, "title", p, where, default="") or _tidy(cid)
        role = get_str(tab, "role", p, where, default="")
        if role and role not in ROLES:
            raise BonesimError(f"'role' must be one of {list(ROLES)}, got {role!r}",
                               p, where)
        names = tab["names"]
        if not isinstance(names, list) or not names or not all(
                isinstance(n, str) and n.strip() for n in names):
            raise BonesimError("'names' must be a list of non-empty strings", p, where)
        phrases = tuple(_words(n, aliases) for n in names)
        classes[cid] = AnatomyClass(cid, kind, flags["monitor"],
                                    _colors(tab["colors"], p, where), phrases, role, title,
                                    flags["nerve"] or flags["monitor"])
    view = {}
    for k, v in doc["view"].items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise BonesimError(f"'{k}' must be a finite number, got {v!r}", p, "view")
        view[k] = float(v)
    return AnatomyTable(classes, aliases, kind_colors, fallback, neighbour, min_de,
                        warn_de, view, p, analysis)


def load_table(path: str | Path | None = None) -> AnatomyTable:
    """Read and check an anatomy table (default: the shipped one; cached)."""
    return _load_table(str(Path(path).resolve()) if path is not None
                       else str(default_table_path()))


# ------------------------------------------------------------------ names
def normalize_name(name: str, table: AnatomyTable | None = None) -> tuple[str, ...]:
    """The words a structure name is matched on (see ``anatomy.toml``).

    Examples
    --------
    >>> normalize_name("Facial_Nerve")
    ('facial', 'nerve')
    >>> normalize_name("n. VII")
    ('nerve', '7')
    >>> normalize_name("CN7")
    ('cranial', 'nerve', '7')
    """
    table = load_table() if table is None else table
    return _words(str(name), table.aliases)


def _contains(words: tuple, phrase: tuple) -> bool:
    n = len(phrase)
    return any(words[i:i + n] == phrase for i in range(len(words) - n + 1))


def classify(name: str, table: AnatomyTable | None = None) -> AnatomyClass | None:
    """The anatomical class a structure name reads as, or None.

    The longest matching phrase (most words, then most letters) wins; ties go
    to the class listed first in the table.
    """
    table = load_table() if table is None else table
    words = _words(str(name), table.aliases)
    best, score = None, (0, 0)
    for cls in table.classes.values():
        for phrase in cls.names:
            s = (len(phrase), sum(len(w) for w in phrase))
            if s > score and _contains(words, phrase):
                best, score = cls, s
    return best


_TITLE_WORD = re.compile(r"[A-Za-z][a-z]+$|[a-z]$")


def _tidy(text: str) -> str:
    """A name written out for the screen: underscores and camelCase become
    spaces, sentence case; words in capitals (``IAC``) and words mixing
    letters otherwise (``McEwen``) are kept."""
    text = re.sub(r"(?<=[a-z])(?=[A-Z][a-z])", " ", str(text))
    words = re.sub(r"[_\s]+", " ", text).strip().split(" ")
    out = [w.lower() if _TITLE_WORD.match(w) else w for w in words]
    if out and out[0]:
        out[0] = out[0][0].upper() + out[0][1:]
    return " ".join(out)


def _abbreviated(text: str, table: AnatomyTable) -> bool:
    """Every word of ``text`` an [aliases] abbreviation of at most four letters,
    a number or a Roman numeral, and at least one an abbreviation."""
    raw = _words(text, {})
    short = [w in table.aliases and len(w) <= 4 and table.aliases[w] != (w,) for w in raw]
    return any(short) and all(s or w.isdigit() or w in _ROMAN for s, w in zip(short, raw))


@functools.lru_cache(maxsize=1024)
def _clinical(name: str, path: str) -> str:
    table = _load_table(path)
    if _abbreviated(name, table):
        cls = classify(name, table)
        if cls is not None:
            words = _words(name, table.aliases)
            if any(w.isdigit() for w in words) and words in cls.names:
                return cls.title
            return _tidy(" ".join(words))
    return _tidy(name)


def clinical_name(name: str, table: AnatomyTable | None = None) -> str:
    """The name a structure shows on screen (window, HUD, monitor trace,
    legends, pictures, the commands' text); files keep ``name`` itself.

    A name written out is tidied (underscores and camelCase to spaces,
    sentence case, capitals kept: ``facial_nerve`` -> ``Facial nerve``,
    ``IAC_contents`` -> ``IAC contents``). An abbreviation the table reads
    (every word an ``[aliases]`` abbreviation of at most four letters, a
    number or a Roman numeral) is written out: its expansion (``SS`` ->
    ``Sigmoid sinus``, ``ICA`` -> ``Internal carotid artery``), or, when
    the expansion holds a number and is one of its class's names, the
    class's ``title`` (``CN7``, ``n. VII`` -> ``Facial nerve``). Applying it
    to its own result changes nothing.

    Parameters
    ----------
    name : str
        The structure's name (as in the manifest).
    table : AnatomyTable, optional
        Default: the shipped table.

    Examples
    --------
    >>> clinical_name("sigmoid_sinus")
    'Sigmoid sinus'
    >>> clinical_name("FN"), clinical_name("CN7")
    ('Facial nerve', 'Facial nerve')
    """
    path = str(default_table_path()) if table is None else str(table.path)
    return _clinical(str(name), path)


def default_kind(name: str, table: AnatomyTable | None = None) -> str:
    """Kind of a structure known only by name: its class's kind, else
    ``"critical"`` (an unknown structure is kept safe)."""
    cls = classify(name, table)
    return cls.kind if cls is not None else "critical"


def default_monitor(name: str, kind: str, table: AnatomyTable | None = None) -> bool:
    """Whether the nerve monitor watches a structure unless told otherwise:
    its name reads as a class the monitor watches by default (a
    mastoidectomy's: the facial nerve, the chorda tympani) and its kind is not
    bone."""
    cls = classify(name, table)
    return kind != "bone" and cls is not None and cls.monitor


def monitor_available(name: str, kind: str, table: AnatomyTable | None = None) -> bool:
    """Whether a structure is a nerve the monitor could watch (its name reads
    as a nerve class and its kind is not bone), watched by default or not.
    ``bonesim case-info`` lists those left off as available."""
    cls = classify(name, table)
    return kind != "bone" and cls is not None and cls.nerve


def default_color(name: str, kind: str, table: AnatomyTable | None = None
                  ) -> tuple[int, int, int]:
    """The palette colour of a structure: its class's first colour, else its
    kind's."""
    table = load_table() if table is None else table
    cls = classify(name, table)
    return tuple((cls.colors if cls is not None else table.kind_colors[kind])[0])


# --------------------------------------------------------------- neighbours
def neighbours(labels: np.ndarray, n_structures: int, spacing_mm, within_mm: float,
               origin_mm=(0.0, 0.0, 0.0), cell_mm: float | None = None) -> np.ndarray:
    """Which structures touch or lie within ``within_mm`` of each other.

    Measured on the labels pooled onto a fixed lattice of ``cell_mm`` cells
    of the case frame, a structure counting in every cell it reaches
    (:func:`bonesim.io.neighbours.neighbours`, which says the rule): the same
    anatomy gives the same neighbours whatever grid it comes on.

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (0 empty), axes x, y, z.
    n_structures : int
        Number of structures (indices 1 .. n).
    spacing_mm : float or (3,) float
        Voxel edge along x, y, z [mm].
    within_mm : float
        Largest gap between neighbours [mm]: with ``cell_mm`` the voxel edge
        (the default) and the voxel centres on the lattice, two structures are
        neighbours when a voxel centre of one lies within ``spacing_mm +
        within_mm`` of a voxel centre of the other (voxels sharing a face
        have a gap of 0).
    origin_mm : (3,) float
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    cell_mm : float, optional
        Lattice cell edge [mm] (cases use ``analysis_mm`` of the table).

    Returns
    -------
    (n, n) bool
        Symmetric, ``[s - 1, t - 1]`` for structures ``s`` and ``t``; the
        diagonal is False.
    """
    from bonesim.io import neighbours as _nb

    return _nb.neighbours(labels, n_structures, spacing_mm, within_mm, origin_mm, cell_mm)


def case_neighbours(native, n_structures: int, table: AnatomyTable | None = None
                    ) -> np.ndarray:
    """Neighbours of a case's structures for its display colours: measured on
    its source-resolution labels (``native``, a
    :class:`bonesim.io.volumes.NativeLabels`) on the table's fixed
    ``analysis_mm`` lattice within ``neighbour_mm``, so the same source gives
    the same neighbours at every ``voxel_mm``.
    """
    table = load_table() if table is None else table
    return neighbours(native.labels, n_structures, native.spacing_mm, table.neighbour_mm,
                      native.origin_mm, table.analysis_mm)


# ------------------------------------------------------------------ colours
def _lab(rgb) -> np.ndarray:
    from skimage.color import rgb2lab

    return rgb2lab(np.asarray(rgb, dtype=float).reshape(-1, 1, 3) / 255.0)[:, 0, :]


def delta_e(a, b) -> np.ndarray:
    """CIEDE2000 colour difference between RGB colours (0-255), broadcast over
    leading axes of ``(..., 3)`` arrays."""
    from skimage.color import deltaE_ciede2000

    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    shape = np.broadcast_shapes(a.shape, b.shape)
    la = _lab(np.broadcast_to(a, shape).reshape(-1, 3))
    lb = _lab(np.broadcast_to(b, shape).reshape(-1, 3))
    return deltaE_ciede2000(la, lb).reshape(shape[:-1])


def resolve_colors(colors: Sequence, sources: Sequence[str], candidates: Sequence,
                   adjacent: np.ndarray, min_delta_e: float) -> list[tuple[int, int, int]]:
    """Display colours with neighbours kept apart, changing only defaults.

    Structures are settled strongest colour source first (:data:`COLOR_SOURCES`;
    ``"manifest"`` colours are never changed), in index order within a source.
    A structure whose colour lies within ``min_delta_e`` of a neighbour settled
    before it takes the first of its candidates that clears every such
    neighbour, else the candidate farthest from its nearest one.

    Parameters
    ----------
    colors : sequence of (3,) int
        Starting colour per structure.
    sources : sequence of str
        Colour source per structure (:data:`COLOR_SOURCES`).
    candidates : sequence of sequence of (3,) int
        Alternative colours per structure, in preference order.
    adjacent : (n, n) bool
        Neighbour matrix (:func:`neighbours`).
    min_delta_e : float
        Least CIEDE2000 difference between neighbours.

    Returns
    -------
    list of (3,) int
    """
    n = len(colors)
    adjacent = np.asarray(adjacent, dtype=bool)
    if adjacent.shape != (n, n) or len(sources) != n or len(candidates) != n:
        raise ValueError("colors, sources, candidates and adjacent must agree in size")
    bad = sorted(set(sources) - set(COLOR_SOURCES))
    if bad:
        raise ValueError(f"unknown colour source(s) {bad}")
    out = [tuple(int(v) for v in c) for c in colors]
    order = sorted(range(n), key=lambda s: (COLOR_SOURCES.index(sources[s]), s))
    settled: list[int] = []
    for s in order:
        if sources[s] != "manifest":
            near = [t for t in settled if adjacent[s, t]]
            if near:
                theirs = np.array([out[t] for t in near], dtype=float)
                if delta_e(out[s], theirs).min() < min_delta_e:
                    options = [tuple(int(v) for v in c) for c in candidates[s]]
                    options = [out[s]] + [c for c in options if c != out[s]]
                    gaps = delta_e(np.array(options, float)[:, None, :],
                                   theirs[None, :, :]).min(axis=1)
                    ok = np.flatnonzero(gaps >= min_delta_e)
                    out[s] = options[int(ok[0]) if ok.size else int(np.argmax(gaps))]
        settled.append(s)
    return out
