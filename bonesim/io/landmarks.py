"""The landmarks of a cortical mastoidectomy, found in any labelling.

Real segmentations differ: the sigmoid sinus and the dura may share one label,
the tegmen is rarely labelled (it is the bone between the middle-fossa dura and
the air cells), the antrum almost never (it is air), and the volume may be cut
so that the mastoid touches its edge. This module finds each landmark from the
names it can read and from geometry where names are missing or merged, and
says for each where it came from and how sure it is.

Frame
-----
Case frame, LPS [mm]: ``+x`` patient left, ``+y`` posterior, ``+z``
superior; arrays indexed ``[i, j, k]`` along x, y, z. For a left ear lateral
is ``+x``, for a right one ``-x``; the *lateral coordinate* of a point is its
distance along the lateral direction.

The analysis grid
-----------------
Landmarks are read on a grid no finer than ``[analysis] voxel_mm`` of
``bonesim/data/landmarks.toml``: a finer label map is pooled in blocks of
``f^3`` voxels, a cell taking the most important structure present in it
(critical over soft over bone over air, then the higher index), so thin
nerves survive and the cost does not grow with the resolution.

Groups and split labels
-----------------------
Structures are put in landmark groups by the anatomical classes their names
read as (:mod:`bonesim.io.anatomy`, every class whose phrase appears in the
name, not only the best one): ``sinus``, ``tegmen`` (middle-fossa dura),
``dura`` (other dura), ``labyrinth``, ``middle_ear`` (ossicles, drum, middle-ear
air), ``ear_canal``, ``facial_nerve``, ``jugular``, ``carotid``, ``iac``. A label
whose name reads as both a sinus and dura (``"Sinus and dura"``), or a sinus
label whose thin part holds ``[split] sheet_share`` of it, is split by
thickness (:func:`split_channel`): the sinus is the channel whose core lies
deeper than ``core_mm`` inside the label, grown back by ``grow_mm``; the rest
is dura. Of all dura, the part nearest the middle ear (or the labyrinth) is
the tegmen: the middle-fossa floor lies a few mm above the epitympanum, the
posterior fossa's dura much further away.

Landmarks (:func:`find_landmarks`)
---------------------------------
``ear_canal``
    its axis and radius: a labelled canal; else the canal opening seen as an
    air channel through the lateral cortex (a pit in the lateral height map,
    :func:`find_canal_pits`); else lateral to the middle ear.
``sigmoid_sinus``
    the sinus's anterior edge within ``[sinus] band_mm`` of the canal's height.
``tegmen``
    the lowest middle-fossa dura over the mastoid (within ``[tegmen] band_mm``
    of the canal front to back, above the canal).
``sinodural_angle``
    where the tegmen meets the sinus.
``macewen``
    Macewen's triangle on the cortex: behind and above the canal, below the
    temporal line (about the tegmen's height).
``antrum``
    the largest air space inside the bone behind the canal's wall, below the
    tegmen and lateral to the labyrinth, nearest where it is expected (about
    13 mm under Macewen's triangle); else that expected point (estimated).
``lateral_canal``
    the most lateral part of the labyrinth near the antrum (the bulge of the
    lateral semicircular canal on the antrum's medial wall).
``facial_nerve``
    the facial nerve's point nearest the antrum and its lowest point.
``mastoid_tip``
    the lowest bone behind the canal, or where the volume's edge cuts it.
``middle_ear``, ``labyrinth``
    centroids of their groups.

Every landmark has a ``source`` sentence and a ``confidence``:
``"labelled"`` (a structure of its own), ``"split"`` (part of a merged label),
``"found"`` (from geometry: an air space, a pit, the cortex) or
``"estimated"`` (from where it must be relative to the others). What cannot
be found is listed in :attr:`Landmarks.missing`.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io import anatomy as _anatomy
from bonesim.tomlfile import read_toml

__all__ = ["GROUPS", "CONFIDENCES", "Landmark", "Landmarks", "LandmarkParams",
           "load_params", "analysis_grid", "structure_groups", "split_channel",
           "group_masks", "lateral_height_map", "find_canal_pits", "find_landmarks",
           "inside_hull"]

#: Landmark groups and the anatomical classes (``anatomy.toml``) that feed them.
GROUPS = {
    "sinus": ("sigmoid_sinus",),
    "tegmen": ("middle_fossa_dura",),
    "dura": ("posterior_fossa_dura", "dura"),
    "labyrinth": ("labyrinth", "cochlea"),
    "middle_ear": ("ossicles", "malleus", "incus", "stapes", "tympanic_membrane",
                   "middle_ear"),
    "ear_canal": ("ear_canal",),
    "facial_nerve": ("facial_nerve",),
    "jugular": ("jugular_bulb",),
    "carotid": ("carotid_artery",),
    "iac": ("internal_auditory_canal", "vestibular_nerve", "cochlear_nerve",
            "vestibulocochlear_nerve"),
}
#: How sure a landmark is, surest first.
CONFIDENCES = ("labelled", "split", "found", "estimated")
#: Pooling rank of each kind (higher wins a pooled cell).
_KIND_RANK = {"critical": 3, "soft": 2, "bone": 1}


@dataclass(frozen=True)
class Landmark:
    """One landmark.

    Attributes
    ----------
    name : str
        Key in :attr:`Landmarks.items` (``"antrum"``).
    point_mm : (3,) float
        Its representative point, case frame [mm].
    source : str
        Where it came from, one sentence (for ``bonesim case-info``).
    confidence : str
        One of :data:`CONFIDENCES`.
    detail : dict
        Numbers behind it (``radius_mm``, ``edge_mm``, ...), JSON-ready.
    """

    name: str
    point_mm: tuple
    source: str
    confidence: str
    detail: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Landmarks:
    """The landmarks of one case.

    Attributes
    ----------
    side : str
        ``"left"`` or ``"right"``.
    items : dict of str -> Landmark
    missing : tuple of str
        One sentence per landmark that could not be found or estimated.
    notes : tuple of str
        How the labels were read (groups, splits).
    cortex : dict
        The lateral height map the landmarks were read on: ``height`` ((ny,
        nz) lateral coordinate of the most lateral bone [mm], NaN where none),
        ``y0``, ``z0`` (column centres of index 0 [mm]), ``h`` (pitch [mm]) and
        ``origin_mm`` (centre of the analysis grid's cell (0, 0, 0)).
    masks : dict of str -> (nx, ny, nz) bool
        The landmark groups on the analysis grid (merged labels split; the
        grid's pitch and origin are ``cortex["h"]`` and ``cortex["origin_mm"]``).
    """

    side: str
    items: dict
    missing: tuple = ()
    notes: tuple = ()
    cortex: dict = field(default_factory=dict, compare=False, repr=False)
    masks: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def lateral(self) -> np.ndarray:
        """Unit lateral direction, case frame."""
        return np.array([1.0 if self.side == "left" else -1.0, 0.0, 0.0])

    def get(self, name: str) -> Landmark | None:
        return self.items.get(name)

    def point(self, name: str) -> np.ndarray | None:
        lm = self.items.get(name)
        return None if lm is None else np.asarray(lm.point_mm, float)

    def lines(self) -> list[str]:
        """One line per landmark (``bonesim case-info``)."""
        out = []
        for lm in self.items.values():
            p = ", ".join(f"{c:.1f}" for c in lm.point_mm)
            out.append(f"{lm.name.replace('_', ' ')}: [{p}] mm, {lm.confidence}: "
                       f"{lm.source}")
        out += [f"missing: {m}" for m in self.missing]
        return out

    def as_dict(self) -> dict:
        """JSON-ready summary."""
        return {"side": self.side,
                "landmarks": {k: {"point_mm": [round(float(c), 3) for c in v.point_mm],
                                  "source": v.source, "confidence": v.confidence,
                                  "detail": v.detail} for k, v in self.items.items()},
                "missing": list(self.missing), "notes": list(self.notes)}


# ------------------------------------------------------------- parameters
@dataclass(frozen=True)
class LandmarkParams:
    """The tables of ``landmarks.toml`` (see the file), as nested dicts."""

    tables: dict

    def __getitem__(self, key: str) -> dict:
        return self.tables[key]


_SECTIONS = {
    "analysis": ("voxel_mm",),
    "split": ("core_mm", "grow_mm", "min_sinus_mm3", "sheet_share", "near_dura_mm"),
    "canal": ("radius_mm", "length_mm"),
    "tegmen": ("above_canal_mm", "band_mm"),
    "sinus": ("band_mm", "behind_wall_mm"),
    "antrum": ("min_radius_mm", "hull_mm", "distance_weight", "depth_mm",
               "behind_wall_mm", "height_fraction", "lateral_of_canal_mm"),
    "macewen": ("temporal_line_below_tegmen_mm",),
}


@functools.lru_cache(maxsize=4)
def _load(path: str) -> LandmarkParams:
    from bonesim.tomlfile import check_keys, get_number

    p = Path(path)
    doc = read_toml(p)
    check_keys(doc, tuple(_SECTIONS), p, "top level", required=tuple(_SECTIONS))
    tables = {}
    for sec, keys in _SECTIONS.items():
        check_keys(doc[sec], keys, p, sec, required=keys)
        tables[sec] = {k: float(get_number(doc[sec], k, p, sec, minimum=0.0)) for k in keys}
    if not tables["analysis"]["voxel_mm"] > 0:
        raise BonesimError("'voxel_mm' must be > 0", p, "analysis")
    return LandmarkParams(tables)


def load_params(path: str | Path | None = None) -> LandmarkParams:
    """Read ``landmarks.toml`` (default: the shipped one; cached)."""
    if path is None:
        from bonesim.resources import data_path

        path = data_path("landmarks.toml")
    return _load(str(Path(path).resolve()))


# ---------------------------------------------------------- analysis grid
def analysis_grid(labels: np.ndarray, spacing_mm: float, origin_mm, kinds: Sequence[str],
                  voxel_mm: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Pool a label map onto a grid no finer than ``voxel_mm``.

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure indices (``s >= 1`` is structure ``s - 1``), axes x, y, z.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    kinds : sequence of str
        Kind per structure.
    voxel_mm : float
        Coarsest wanted edge [mm]: blocks of ``f = max(1, round(voxel_mm /
        spacing_mm))`` voxels per axis become one cell.

    Returns
    -------
    labels : (mx, my, mz) uint8
        A cell takes the structure of the highest kind rank present in its
        block (critical 3, soft 2, bone 1, empty 0), then the highest index;
        blocks cut by the grid's edge pool what they hold.
    spacing_mm : float
        ``f * spacing_mm``.
    origin_mm : (3,) float64
        Centre of cell (0, 0, 0) [mm].
    """
    labels = np.asarray(labels)
    h = float(spacing_mm)
    origin = np.asarray(origin_mm, float).reshape(3)
    f = max(1, int(math.floor(voxel_mm / h + 0.5)))
    if f == 1:
        return labels, h, origin
    n = len(kinds)
    rank = np.zeros(256, np.uint16)
    for s, k in enumerate(kinds, start=1):
        rank[s] = (_KIND_RANK.get(k, 3) << 8) | s
    back = np.zeros(1 << 10, np.uint8)
    back[rank[1:n + 1]] = np.arange(1, n + 1, dtype=np.uint8)
    nx, ny, nz = labels.shape
    m = [-(-d // f) for d in labels.shape]
    out = np.zeros(m, np.uint8)
    pad_y, pad_z = m[1] * f - ny, m[2] * f - nz
    for i in range(m[0]):                             # one slab of f x-planes
        slab = rank[labels[i * f:(i + 1) * f]]
        if pad_y or pad_z:
            slab = np.pad(slab, ((0, 0), (0, pad_y), (0, pad_z)))
        r = slab.reshape(slab.shape[0], m[1], f, m[2], f).max(axis=(0, 2, 4))
        out[i] = back[r]
    return out, h * f, origin + h * (f - 1) / 2.0


# ------------------------------------------------------------------ groups
def structure_groups(structures, table=None) -> list[set]:
    """Landmark groups per structure, from the classes its name reads as.

    Every class one of whose phrases appears in the (normalised) name counts,
    plus the structure's assigned class (``structure.anatomy``); so ``"Sinus
    and dura"`` is in both ``sinus`` and ``dura``. Bone structures are in no
    group.
    """
    table = _anatomy.load_table() if table is None else table
    cls_group = {c: g for g, cs in GROUPS.items() for c in cs}
    out = []
    for s in structures:
        groups = set()
        if s.kind != "bone":
            words = _anatomy.normalize_name(s.name, table)
            ids = {getattr(s, "anatomy", "") or ""}
            for cls in table.classes.values():
                if any(_contains(words, ph) for ph in cls.names):
                    ids.add(cls.id)
            best = _anatomy.classify(s.name, table)
            if best is not None:
                ids.add(best.id)
            # "sinus tympani" and the like: a longer phrase of another class
            # that contains the sinus's word is not a sinus
            if best is not None and best.id not in ("sigmoid_sinus",) and \
                    cls_group.get(best.id) not in ("sinus", "tegmen", "dura"):
                ids = {best.id} | ({getattr(s, "anatomy", "")} - {""})
            groups = {cls_group[c] for c in ids if c in cls_group}
        out.append(groups)
    return out


def _contains(words, phrase) -> bool:
    n = len(phrase)
    return any(tuple(words[i:i + n]) == tuple(phrase) for i in range(len(words) - n + 1))


def split_channel(mask: np.ndarray, spacing_mm: float, core_mm: float, grow_mm: float,
                  min_mm3: float) -> np.ndarray:
    """The channel (thick) part of a mask; the rest is sheet.

    Parameters
    ----------
    mask : (nx, ny, nz) bool
    spacing_mm : float
        Voxel edge [mm].
    core_mm : float
        Voxels deeper than this inside the mask (Euclidean distance to the
        nearest voxel outside it) are the channel's core [mm].
    grow_mm : float
        The core is grown back within the mask by this much [mm].
    min_mm3 : float
        Channel parts smaller than this are dropped [mm^3].

    Returns
    -------
    (nx, ny, nz) bool
        The channel; ``mask & ~channel`` is the sheet.
    """
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    out = np.zeros(mask.shape, bool)
    if not mask.any():
        return out
    box = ndimage.find_objects(mask.astype(np.uint8))[0]
    pad = 2
    box = tuple(slice(max(b.start - pad, 0), min(b.stop + pad, n))
                for b, n in zip(box, mask.shape))
    sub = mask[box]
    depth = ndimage.distance_transform_edt(sub, sampling=spacing_mm)
    core = depth > core_mm
    if not core.any():
        return out
    steps = max(1, int(math.ceil(grow_mm / spacing_mm)))
    grown = ndimage.binary_dilation(core, iterations=steps, mask=sub)
    lab, n = ndimage.label(grown)
    if n:
        sizes = ndimage.sum_labels(np.ones_like(lab), lab, np.arange(1, n + 1))
        keep = np.flatnonzero(sizes * spacing_mm ** 3 >= min_mm3) + 1
        out[box] = np.isin(lab, keep)
    return out


def group_masks(labels: np.ndarray, spacing_mm: float, structures, groups, params,
                table=None) -> tuple[dict, list[str]]:
    """Boolean masks of the landmark groups on ``labels``, merged labels split.

    Returns
    -------
    masks : dict of str -> (nx, ny, nz) bool
        One per group present (see :data:`GROUPS`).
    notes : list of str
        How merged labels were split.
    """
    sp = params["split"]
    masks: dict = {}
    notes = []

    def add(g, m):
        if m.any():
            masks[g] = masks[g] | m if g in masks else m

    for s, (st, gs) in enumerate(zip(structures, groups), start=1):
        if not gs:
            continue
        m = labels == s
        if not m.any():
            continue
        mixed = "sinus" in gs and ({"dura", "tegmen"} & gs)
        if "sinus" in gs:
            ch = split_channel(m, spacing_mm, sp["core_mm"], sp["grow_mm"],
                               sp["min_sinus_mm3"])
            sheet = m & ~ch
            share = sheet.sum() / max(m.sum(), 1)
            if mixed or (share >= sp["sheet_share"] and ch.any()):
                add("sinus", ch)
                add("dura", sheet)
                why = "its name says sinus and dura" if mixed else \
                    f"{100 * share:.0f} % of it is a thin sheet"
                notes.append(f"{_anatomy.clinical_name(st.name)!r} split by thickness "
                             f"({why}): the channel "
                             f"({ch.sum() * spacing_mm ** 3:.0f} mm^3) is the sigmoid "
                             f"sinus, the sheet ({sheet.sum() * spacing_mm ** 3:.0f} mm^3)"
                             " dura")
                continue
        for g in gs:
            add(g, m)
    return masks, notes
def lateral_height_map(mask: np.ndarray, spacing_mm: float, origin_mm, side: str
                       ) -> np.ndarray:
    """Lateral coordinate of the most lateral voxel of ``mask`` per column.

    Parameters
    ----------
    mask : (nx, ny, nz) bool
        Axes x, y, z.
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    side : {"left", "right"}
        Lateral is ``+x`` for a left ear, ``-x`` for a right one.

    Returns
    -------
    (ny, nz) float64
        ``x`` (left) or ``-x`` (right) of that voxel's centre [mm]; NaN where
        the column holds no voxel of ``mask``.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    mask = np.asarray(mask).astype(bool, copy=False)
    if mask.ndim != 3:
        raise ValueError(f"mask must be 3-D, got shape {mask.shape}")
    h = float(spacing_mm)
    origin = np.asarray(origin_mm, float).reshape(3)
    lat = 1.0 if side == "left" else -1.0
    nx = mask.shape[0]
    has = mask.any(axis=0)
    if lat > 0:
        i = nx - 1 - np.argmax(mask[::-1], axis=0)
    else:
        i = np.argmax(mask, axis=0)
    out = lat * (origin[0] + h * i)
    out[~has] = np.nan
    return out


def find_canal_pits(height: np.ndarray, spacing_mm: float, closing_mm: float,
                    depth_mm: float, min_area_mm2: float, max_area_mm2: float,
                    rim_mm: float = 1.5, rim_fraction: float = 0.8) -> list[dict]:
    """Canal-like pits of a lateral height map (openings into the bone).

    A pit is a connected set of columns, inside the bone's silhouette (holes
    in it included), lying more than ``depth_mm`` below the map's grey
    closing with a ``(2 r + 1)``-column square, ``r = closing_mm / spacing``,
    and ringed by cortex: at least ``rim_fraction`` of the columns within
    ``rim_mm`` around it hold bone that is not itself in a pit (an opening
    in the cortex, not a notch at the bone's edge).

    Parameters
    ----------
    height : (ny, nz) float
        :func:`lateral_height_map` (NaN outside the bone) [mm].
    spacing_mm : float
        Column pitch [mm].
    closing_mm, depth_mm : float
        Closing half-width and least pit depth [mm].
    min_area_mm2, max_area_mm2 : float
        Accepted pit areas [mm^2].
    rim_mm, rim_fraction : float
        Width of the ring checked around a pit [mm] and the share of it that
        must be cortex.

    Returns
    -------
    list of dict
        ``j, k`` (column centroid, fractional indices), ``area_mm2``,
        ``depth_mm`` (mean depth below the closing), largest area first.
    """
    from scipy import ndimage

    height = np.asarray(height, dtype=float)
    has = np.isfinite(height)
    if not has.any():
        return []
    inside = ndimage.binary_fill_holes(has)
    floor = float(np.nanmin(height))
    h = np.where(has, height, floor)
    r = max(1, int(round(closing_mm / spacing_mm)))
    closed = ndimage.grey_closing(h, size=(2 * r + 1, 2 * r + 1), mode="nearest")
    depth = closed - h
    pit = inside & (depth > depth_mm)
    lab, n = ndimage.label(pit)
    out = []
    if n == 0:
        return out
    idx = np.arange(1, n + 1)
    counts = ndimage.sum_labels(np.ones_like(h), lab, idx)
    cents = ndimage.center_of_mass(np.ones_like(h), lab, idx)
    mean_depth = ndimage.mean(depth, lab, idx)
    cortex = has & ~(depth > depth_mm)
    ring_r = max(1, int(math.ceil(rim_mm / spacing_mm)))
    boxes = ndimage.find_objects(lab)
    for n_pit, (c, cen, d, box) in enumerate(zip(counts, cents, mean_depth, boxes), 1):
        area = float(c) * spacing_mm ** 2
        if not min_area_mm2 <= area <= max_area_mm2:
            continue
        lo = [max(b.start - ring_r, 0) for b in box]
        hi = [min(b.stop + ring_r, n) for b, n in zip(box, h.shape)]
        sub = lab[lo[0]:hi[0], lo[1]:hi[1]] == n_pit
        ring = ndimage.binary_dilation(sub, iterations=ring_r) & ~sub
        if (lo[0] == 0 or lo[1] == 0 or hi[0] == h.shape[0]
                           or hi[1] == h.shape[1]):
            continue                                  # runs off the map: no rim
        rim = cortex[lo[0]:hi[0], lo[1]:hi[1]][ring]
        if rim.size and rim.mean() >= rim_fraction:
            out.append({"j": float(cen[0]), "k": float(cen[1]), "area_mm2": area,
                        "depth_mm": float(d)})
    out.sort(key=lambda p: -p["area_mm2"])
    return out




# --------------------------------------------------------------- landmarks
def _pct(values, q):
    return float(np.percentile(values, q))


def inside_hull(solid: np.ndarray, reach: int) -> np.ndarray:
    """Cells inside a solid's hull, not out in the open.

    Parameters
    ----------
    solid : (nx, ny, nz) bool
        The solid's cells (any axis order: the test is the same along each).
    reach : int
        How far a solid cell may lie [cells].

    Returns
    -------
    (nx, ny, nz) bool
        Cells with a ``solid`` cell within ``reach`` cells along each of the six
        axis directions.
    """
    out = np.ones(solid.shape, bool)
    for a in range(3):
        for flip in (False, True):
            m = np.flip(solid, axis=a) if flip else solid
            # distance (in cells) to the nearest solid cell at or before, along +a
            idx = np.arange(m.shape[a]).reshape([-1 if b == a else 1 for b in range(3)])
            last = np.where(m, idx, -10 ** 6)
            last = np.maximum.accumulate(last, axis=a)
            ok = (idx - last) <= reach
            out &= np.flip(ok, axis=a) if flip else ok
    return out


def find_landmarks(labels: np.ndarray, spacing_mm: float, origin_mm, structures,
                   side: str, params: LandmarkParams | None = None,
                   view_params: dict | None = None) -> Landmarks:
    """The landmarks of a mastoidectomy (see the module docstring).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s >= 1`` is ``structures[s - 1]``), axes
        x, y, z of the LPS case frame.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``name``, ``kind`` and (optionally) ``anatomy``.
    side : {"left", "right"}
        The ear (lateral is ``+x`` for a left ear).
    params : LandmarkParams, optional
        Default: the shipped ``landmarks.toml``.
    view_params : dict, optional
        The ``[view]`` table of ``anatomy.toml`` (canal pits).

    Returns
    -------
    Landmarks

    Raises
    ------
    ValueError
        No bone, or inconsistent inputs.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    p = load_params() if params is None else params
    vp = dict(_anatomy.load_table().view) if view_params is None else view_params
    kinds = [s.kind for s in structures]
    lab, h, origin = analysis_grid(labels, spacing_mm, origin_mm, kinds,
                                   p["analysis"]["voxel_mm"])
    groups = structure_groups(structures)
    masks, notes = group_masks(lab, h, structures, groups, p)
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    bone = np.isin(lab, bone_idx)
    if not bone.any():
        raise ValueError("no bone in the volume: no landmarks")
    lat = 1.0 if side == "left" else -1.0
    shape = np.array(lab.shape)
    ys = origin[1] + h * np.arange(shape[1])
    zs = origin[2] + h * np.arange(shape[2])
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    height = lateral_height_map(bone, h, origin, side)
    has = np.isfinite(height)
    items: dict = {}
    missing: list = []
    names = [s.name for s in structures]
    cortex = {"height": height, "y0": float(ys[0]), "z0": float(zs[0]), "h": h,
              "origin_mm": origin}

    def who(group):
        return ", ".join(repr(_anatomy.clinical_name(n)) for n, g in zip(names, groups)
                         if group in g or (group == "dura" and "tegmen" in g))

    def pts(group):
        m = masks.get(group)
        return None if m is None else origin + h * np.argwhere(m)

    def cortex_at(y, z, radius=2.0):
        d2 = (yy - y) ** 2 + (zz - z) ** 2
        disc = has & (d2 <= radius ** 2)
        if not disc.any():
            if not has.any():
                return math.nan
            disc = np.zeros_like(has)
            disc[np.unravel_index(np.argmin(np.where(has, d2, np.inf)), d2.shape)] = True
        return float(np.median(height[disc]))

    def put(name, point, source, confidence, **detail):
        items[name] = Landmark(name, tuple(float(c) for c in point), source, confidence,
                               {k: (round(float(v), 3) if isinstance(v, (float, np.floating))
                                    else v) for k, v in detail.items()})

    # -- middle ear and labyrinth
    me_pts, lab_pts = pts("middle_ear"), pts("labyrinth")
    if me_pts is not None:
        put("middle_ear", me_pts.mean(0), f"centre of {who('middle_ear')}", "labelled")
    if lab_pts is not None:
        put("labyrinth", lab_pts.mean(0), f"centre of {who('labyrinth')}", "labelled")

    # -- ear canal: axis (y_c, z_c), radius r_c
    canal = None
    cp = pts("ear_canal")
    if cp is not None:
        y5, y95 = np.percentile(cp[:, 1], [5, 95])
        z5, z95 = np.percentile(cp[:, 2], [5, 95])
        r = float(np.clip(0.25 * ((y95 - y5) + (z95 - z5)) + h / 2, 1.0, 10.0))
        c = cp.mean(0)
        canal = (c[1], c[2], r, f"axis of {who('ear_canal')}", "labelled")
    if canal is None:
        pits = find_canal_pits(height, h, vp["pit_closing_mm"], vp["pit_depth_mm"],
                               vp["pit_min_area_mm2"], vp["pit_max_area_mm2"],
                               vp["pit_rim_mm"], vp["pit_rim_fraction"])
        if pits:
            if me_pts is not None:
                ref = me_pts.mean(0)
                pits.sort(key=lambda q: math.hypot(ys[0] + h * q["j"] - ref[1],
                                                   zs[0] + h * q["k"] - ref[2]))
            q = pits[0]
            canal = (ys[0] + h * q["j"], zs[0] + h * q["k"], math.sqrt(q["area_mm2"] / math.pi),
                     f"the air channel through the lateral cortex (opening "
                     f"{q['area_mm2']:.0f} mm^2, {q['depth_mm']:.0f} mm deep)", "found")
    if canal is None and me_pts is not None:
        c = me_pts.mean(0)
        canal = (c[1], c[2], p["canal"]["radius_mm"],
                 f"lateral to the middle ear ({who('middle_ear')}), no canal seen",
                 "estimated")
    if canal is None:
        missing.append("ear canal: no canal label, no canal opening in the lateral "
                       "cortex and no middle ear to place it by")
        return Landmarks(side, items, tuple(missing), tuple(notes), cortex, masks)
    y_c, z_c, r_c, how, conf = canal
    wall = y_c + r_c                                   # the canal's posterior wall
    put("ear_canal", (lat * cortex_at(y_c, z_c, r_c + 2.0), y_c, z_c), how, conf,
        radius_mm=r_c, posterior_wall_y_mm=wall)

    # -- sigmoid sinus: its anterior edge near the canal's height
    y_s = None
    sp_ = pts("sinus")
    if sp_ is not None:
        band = sp_[np.abs(sp_[:, 2] - z_c) <= p["sinus"]["band_mm"]]
        band = band if len(band) else sp_
        y_s = _pct(band[:, 1], 5)
        front = band[band[:, 1] <= y_s + h]
        conf = "split" if any("split" in n and who("sinus").split(",")[0] in n
                              for n in notes) else "labelled"
        if y_s <= wall:
            missing.append(f"sigmoid sinus ({who('sinus')}): its front (y {y_s:.1f} mm) "
                           "lies in front of the ear canal's posterior wall; not used")
            y_s = None
        else:
            put("sigmoid_sinus", (float(np.median(front[:, 0])), y_s,
                                  float(np.median(front[:, 2]))),
                f"anterior edge of {who('sinus')}" + (" (its channel)" if conf == "split"
                                                       else ""), conf,
                front_y_mm=y_s, behind_canal_wall_mm=y_s - wall)
    if y_s is None:
        y_s_est = wall + p["sinus"]["behind_wall_mm"]
        missing.append(f"sigmoid sinus: not labelled; the cavity's posterior limit is "
                       f"estimated {p['sinus']['behind_wall_mm']:g} mm behind the "
                       "canal's posterior wall")
    else:
        y_s_est = y_s

    # -- tegmen: the lowest middle-fossa dura over the mastoid
    z_t = None
    cand = [a for a in (pts("tegmen"), pts("dura")) if a is not None]
    if cand:
        d = np.concatenate(cand)
        keep = (np.abs(d[:, 1] - y_c) <= p["tegmen"]["band_mm"]) & (d[:, 2] > z_c) \
            & (d[:, 1] < y_s_est)
        if lab_pts is not None:
            keep &= lat * d[:, 0] >= float(np.max(lat * lab_pts[:, 0])) - 5.0
        d = d[keep]
        if len(d):
            z_t = _pct(d[:, 2], 5)
            low = d[d[:, 2] <= z_t + h]
            src = who("tegmen") or who("dura")
            conf = "labelled" if "tegmen" in masks else "split"
            put("tegmen", (float(np.median(low[:, 0])), float(np.median(low[:, 1])), z_t),
                f"lowest dura of {src} over the mastoid", conf, lowest_z_mm=z_t,
                above_canal_mm=z_t - z_c)
    if z_t is None:
        z_t = z_c + r_c + p["tegmen"]["above_canal_mm"]
        put("tegmen", (lat * cortex_at(wall, z_t), wall, z_t),
            f"no dura over the mastoid: estimated {p['tegmen']['above_canal_mm']:g} mm "
            "above the canal's roof", "estimated", lowest_z_mm=z_t)

    # -- sinodural angle
    if y_s is not None:
        near = sp_[np.abs(sp_[:, 2] - z_t) <= 3.0]
        y_sd = _pct(near[:, 1], 5) if len(near) else y_s
        put("sinodural_angle", (lat * cortex_at(y_sd, z_t), y_sd, z_t),
            "where the tegmen's height meets the sinus's front", "found")

    # -- Macewen's triangle on the cortex
    z_tl = max(z_t - p["macewen"]["temporal_line_below_tegmen_mm"], z_c + r_c + h)
    jj = (yy >= y_c) & (yy <= wall) & (zz >= z_c) & (zz <= z_tl)
    jj &= (yy - y_c) ** 2 + (zz - z_c) ** 2 > r_c ** 2
    if jj.any():
        y_m, z_m = float(yy[jj].mean()), float(zz[jj].mean())
    else:
        y_m, z_m = wall, z_c + r_c
    put("macewen", (lat * cortex_at(y_m, z_m), y_m, z_m),
        "behind and above the canal, below the temporal line (the tegmen's height)",
        "found" if items["tegmen"].confidence != "estimated" else "estimated",
        vertices_yz=[[round(y_c, 2), round(z_tl, 2)], [round(wall, 2), round(z_tl, 2)],
                     [round(wall, 2), round(z_c, 2)], [round(y_c, 2), round(z_c + r_c, 2)]])

    # -- lateral semicircular canal (the labyrinth's most lateral part)
    lat_scc = None
    if lab_pts is not None:
        s_lat = lat * lab_pts[:, 0]
        top = lab_pts[s_lat >= np.percentile(s_lat, 98)]
        lat_scc = top.mean(0)

    # -- antrum: the biggest air space inside the bone, where it is expected
    a = p["antrum"]
    surf = cortex_at(y_m, z_m)
    e_lat = surf - a["depth_mm"]
    if lat_scc is not None:
        e_lat = max(e_lat, lat * lat_scc[0] + a["lateral_of_canal_mm"])
    expect = np.array([lat * e_lat, wall + a["behind_wall_mm"],
                       z_c + a["height_fraction"] * (z_t - z_c)])
    found = _find_antrum(lab, bone, h, origin, lat, expect, wall, y_s_est, z_c - r_c, z_t,
                         None if lat_scc is None else lat * lat_scc[0], surf, a)
    if found is not None:
        c, r = found
        put("antrum", c, f"the air space inside the bone (radius {r:.1f} mm) deep to "
            f"Macewen's triangle", "found", radius_mm=r,
            depth_mm=surf - lat * c[0])
    else:
        put("antrum", expect, f"no air space found: estimated {a['depth_mm']:g} mm under "
            "Macewen's triangle, lateral to the lateral semicircular canal", "estimated",
            radius_mm=0.0, depth_mm=surf - e_lat)
    ant = np.asarray(items["antrum"].point_mm)
    if lat_scc is not None:
        near = lab_pts[np.linalg.norm(lab_pts - ant, axis=1) <= 15.0]
        if len(near):
            s_lat = lat * near[:, 0]
            lat_scc = near[s_lat >= np.percentile(s_lat, 95)].mean(0)
        put("lateral_canal", lat_scc, f"the most lateral part of {who('labyrinth')} "
            "near the antrum (the lateral semicircular canal's bulge)",
            "found", distance_to_antrum_mm=float(np.linalg.norm(lat_scc - ant)))
    else:
        missing.append("lateral semicircular canal: no labyrinth label")

    # -- facial nerve
    fp = pts("facial_nerve")
    if fp is not None:
        dn = np.linalg.norm(fp - ant, axis=1)
        q = fp[np.argmin(dn)]
        put("facial_nerve", q, f"the point of {who('facial_nerve')} nearest the antrum",
            "labelled", distance_to_antrum_mm=float(dn.min()),
            lowest_z_mm=float(fp[:, 2].min()),
            depth_under_cortex_mm=cortex_at(q[1], q[2]) - lat * q[0])
    else:
        missing.append("facial nerve: no facial-nerve label (the plan keeps its margin "
                       "from every critical structure it knows)")

    # -- mastoid tip: the lowest bone behind the canal seen from lateral
    behind = has & (yy > wall) & (yy < y_s_est + 10.0)
    if behind.any():
        k = np.argwhere(behind)
        low = k[np.argmin(k[:, 1])]
        cut = low[1] == 0
        put("mastoid_tip", (lat * float(height[tuple(low)]), float(ys[low[0]]),
                            float(zs[low[1]])),
            "cut by the volume's lower edge" if cut else
            "the lowest bone behind the canal, seen from lateral",
            "found", at_volume_edge=bool(cut))
    return Landmarks(side, items, tuple(missing), tuple(notes), cortex, masks)


def _find_antrum(lab, bone, h, origin, lat, expect, wall, y_back, z_low, z_top, lat_lab,
                 surf, a):
    """Centre [mm] and radius [mm] of the antrum candidate with the best
    score (see ``[antrum]`` in ``landmarks.toml``), or None."""
    from scipy import ndimage

    shape = np.array(lab.shape)
    pad = int(math.ceil(a["hull_mm"] / h)) + 2
    lo_mm = np.array([min(lat * (surf + 2.0), lat * (lat_lab if lat_lab is not None
                                                     else surf - 30.0)),
                      wall, z_low])
    hi_mm = np.array([max(lat * (surf + 2.0), lat * (lat_lab if lat_lab is not None
                                                     else surf - 30.0)),
                      y_back, z_top])
    lo = np.clip(np.floor((lo_mm - origin) / h).astype(int) - pad, 0, shape)
    hi = np.clip(np.ceil((hi_mm - origin) / h).astype(int) + pad + 1, 0, shape)
    if np.any(hi - lo < 3):
        return None
    box = tuple(slice(l, u) for l, u in zip(lo, hi))
    sub = lab[box]
    air = sub == 0
    radius = ndimage.distance_transform_edt(air, sampling=h)
    inside = inside_hull(bone[box] | (sub > 0), int(round(a["hull_mm"] / h)))
    peak = (radius == ndimage.maximum_filter(radius, size=3)) & inside \
        & (radius >= a["min_radius_mm"])
    ijk = np.argwhere(peak)
    if not len(ijk):
        return None
    c = origin + h * (ijk + lo)
    r = radius[tuple(ijk.T)]
    ok = (c[:, 1] >= wall) & (c[:, 1] <= y_back) & (c[:, 2] <= z_top) & (c[:, 2] >= z_low)
    ok &= lat * c[:, 0] <= surf - 2.0
    if lat_lab is not None:
        ok &= lat * c[:, 0] >= lat_lab
    if not ok.any():
        return None
    c, r = c[ok], r[ok]
    score = r - a["distance_weight"] * np.linalg.norm(c - expect, axis=1)
    best = int(np.argmax(score))
    return c[best], float(r[best])
