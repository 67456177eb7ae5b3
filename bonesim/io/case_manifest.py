"""Reading a ``case.toml``: every table checked, defaults read from the
anatomy (kinds, colours and monitor flags by name, segments of a 3D Slicer
segmentation). The manifest's layout is documented in :mod:`bonesim.io.case`
and ``docs/cases.md``; :func:`bonesim.io.case.parse_case` is the public entry.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from bonesim.io import anatomy as _anatomy
from bonesim.io import phantom as _phantom
from bonesim.io.case_records import (CASE_FORMATS, DEFAULT_BONE_THRESHOLD_HU, DEFAULT_PATTERN,
                                     DEFAULT_VOXEL_MM, KINDS, MAX_LABEL, SEG_FORMAT, SIDES,
                                     Camera, Case, Structure, Target, VolumeSpec,
                                     check_voxel_mm)
from bonesim.io.case_records import Fragments
from bonesim.errors import BonesimError
from bonesim.io.orientation import parse_orientation
from bonesim.io.segmentation import SEG_SUFFIX, read_seg_segments, segment_keys
from bonesim.io.limits import check
from bonesim.tomlfile import check_keys, get_number, get_str, get_vector, read_toml
from bonesim.io.volumes import MAX_STRUCTURES, UNKNOWN_COLOR_MODES

__all__ = ["parse_manifest"]

_TOP_KEYS = ("case", "volume", "structures", "camera", "target", "physics")
_CASE_KEYS = ("name", "description", "side")
_VOLUME_COMMON = ("format", "voxel_mm")
_VOLUME_KEYS = {
    "phantom": ("seed", "size_mm", "generation"),
    "dicom": ("path", "bone_threshold_hu", "labels"),
    "nrrd": ("path", "bone_threshold_hu", "labels"),
    "nifti": ("path", "bone_threshold_hu", "labels"),
    "label-stack": ("path", "pattern", "size_mm", "unknown_colors", "origin_mm",
                    "orientation"),
    SEG_FORMAT: ("path",),
}
_OWN_ORIENTATION = {"dicom": "DICOM series carry their own orientation",
                    "nrrd": "NRRD files carry their own orientation",
                    "nifti": "NIfTI files carry their own orientation",
                    SEG_FORMAT: "segmentation files carry their own orientation",
                    "phantom": "the phantom is generated in the patient frame"}
_STRUCTURE_KEYS = ("name", "kind", "label", "color", "display_color", "monitor",
                   "segment", "anatomy")
_CAMERA_KEYS = ("eye_mm", "focal_mm", "up")
_TARGET_KEYS = ("description", "structures", "box_mm")
_TOP_KEYS += ("fragments",)
_FRAGMENTS_KEYS = ("speck_voxels",)


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
    for v in vec:                       # physical bounds (bonesim/data/limits.toml)
        check("case_extent_mm", v, path, where, what=f"'{key}'")
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
    fmt = get_str(tab, "format", path, where, choices=CASE_FORMATS)
    if "orientation" in tab and fmt != "label-stack":
        raise BonesimError(f"'orientation' does not apply to format '{fmt}': "
                           f"{_OWN_ORIENTATION.get(fmt, 'it has its own')}; only label "
                           "stacks declare one", path, where)
    allowed = _VOLUME_COMMON + _VOLUME_KEYS[fmt]
    for key in tab:
        if key not in allowed and any(key in ks for ks in _VOLUME_KEYS.values()):
            raise BonesimError(f"key '{key}' does not apply to format '{fmt}'",
                               path, where)
    check_keys(tab, allowed, path, where)
    voxel = check_voxel_mm(tab.get("voxel_mm", DEFAULT_VOXEL_MM), path, where)
    spec = dict(format=fmt, voxel_mm=voxel)
    if fmt == "phantom":
        spec["seed"] = int(get_number(tab, "seed", path, where,
                                      default=_phantom.DEFAULT_SEED, integer=True))
        if "size_mm" in tab:
            spec["size_mm"] = _positive_vector(tab, "size_mm", path, where)
        gen = get_number(tab, "generation", path, where,
                         default=_phantom.LATEST_GENERATION, integer=True)
        if gen not in _phantom.GENERATIONS:
            raise BonesimError(f"'generation' must be one of {list(_phantom.GENERATIONS)}, "
                               f"got {gen}", path, where)
        spec["generation"] = int(gen)
        return VolumeSpec(**spec)
    spec["path"] = _relative(tab, "path", path, where)
    if fmt == SEG_FORMAT:
        if spec["path"] is None:
            raise BonesimError("missing required key 'path' (the .seg.nrrd file)",
                               path, where)
        return VolumeSpec(**spec)
    if fmt == "label-stack":
        if spec["path"] is None:
            raise BonesimError("missing required key 'path'", path, where)
        spec["pattern"] = get_str(tab, "pattern", path, where, default=DEFAULT_PATTERN)
        if "size_mm" not in tab:
            raise BonesimError("missing spacing: a label stack needs 'size_mm' = "
                               "[columns, rows, slices], its physical extent along "
                               "the image axes", path, where)
        spec["size_mm"] = _positive_vector(tab, "size_mm", path, where)
        spec["unknown_colors"] = get_str(tab, "unknown_colors", path, where,
                                         default="error", choices=UNKNOWN_COLOR_MODES)
        if "origin_mm" in tab:
            spec["origin_mm"] = tuple(
                check("coordinate_mm", v, path, where, what="'origin_mm'")
                for v in get_vector(tab, "origin_mm", path, where))
        if "orientation" in tab:
            spec["orientation"] = parse_orientation(tab["orientation"], path, where)
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
    if spec["path"] is None and spec["labels"].name.lower().endswith(SEG_SUFFIX):
        return VolumeSpec(format=SEG_FORMAT, path=spec["labels"], voxel_mm=voxel)
    return VolumeSpec(**spec)


def _segment_lookup(segments, seg_path: Path):
    """Name / ID -> canonical segment key (its name, or its ID when two
    segments share the name)."""
    key = segment_keys(segments)
    exact = {}
    for g in segments:
        exact.setdefault(g.name, key[g.id])
        exact.setdefault(g.id, key[g.id])
    loose = {}
    for g in segments:
        loose.setdefault(_anatomy.normalize_name(g.name), key[g.id])
    return key, exact, loose


def _structures_from_segments(segments, seg_path: Path, path: Path) -> list[dict]:
    key, _, _ = _segment_lookup(segments, seg_path)
    seen: dict = {}
    out = []
    for g in segments:
        name = g.name if g.name not in seen else f"{g.name} ({g.id})"
        seen[name] = True
        out.append({"name": name, "segment": key[g.id], "_segment_color": g.color})
    return out


def _parse_structures(items, path: Path, volume: VolumeSpec) -> tuple[Structure, ...]:
    fmt = volume.format
    seg_path = volume.segmentation
    segments = read_seg_segments(seg_path) if seg_path is not None else None
    table = _anatomy.load_table()
    from_file = False
    if items is None and segments is not None:
        items, from_file = _structures_from_segments(segments, seg_path, path), True
    if not isinstance(items, list) or not items:
        raise BonesimError("need at least one [[structures]] entry", path, "structures")
    if len(items) > MAX_STRUCTURES:
        raise BonesimError(f"at most {MAX_STRUCTURES} structures, got {len(items)}",
                           path, "structures")
    if segments is not None:
        _, exact, loose = _segment_lookup(segments, seg_path)
        seg_color = {}
        for g in segments:
            seg_color.setdefault(exact[g.id], g.color)
    out, names, labels, colors, used_segments = [], {}, {}, {}, {}
    for i, tab in enumerate(items):
        where = f"structures[{i}]"
        seg_default = tab.pop("_segment_color", None) if from_file else None
        required = ("name",) if segments is not None else ("name", "kind")
        check_keys(tab, _STRUCTURE_KEYS, path, where, required=required)
        name = get_str(tab, "name", path, where)
        if not name.strip():
            raise BonesimError("'name' must not be empty", path, where)
        if name in names:
            raise BonesimError(f"duplicate structure name {name!r} (also "
                               f"structures[{names[name]}])", path, where)
        names[name] = i
        anatomy = get_str(tab, "anatomy", path, where, default="")
        if "anatomy" in tab and anatomy not in table.classes:
            raise BonesimError(f"'anatomy' must be one of {sorted(table.classes)}, got "
                               f"{anatomy!r}", path, where)
        if not anatomy:
            cls = _anatomy.classify(name, table)
            anatomy = cls.id if cls is not None else ""
        cls = table.classes.get(anatomy)
        if "kind" in tab or segments is None:
            kind = get_str(tab, "kind", path, where, choices=KINDS)
        else:
            kind = cls.kind if cls is not None else "critical"
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
        segment = None
        if "segment" in tab and segments is None:
            raise BonesimError("'segment' applies only to structures of a 3D Slicer "
                               "segmentation (format 'seg-nrrd')", path, where)
        if segments is not None:
            wanted = get_str(tab, "segment", path, where, default=name)
            segment = exact.get(wanted) or loose.get(_anatomy.normalize_name(wanted))
            if segment is None:
                listed = ", ".join(repr(g.name) for g in segments)
                raise BonesimError(f"no segment {wanted!r} in {seg_path.name}; its "
                                   f"segments: {listed}", path, where)
            if segment in used_segments:
                raise BonesimError(f"segment {segment!r} already used by "
                                   f"{used_segments[segment]!r}", path, where)
            used_segments[segment] = name
            seg_default = seg_color[segment]
        if fmt == "phantom" and name not in _phantom.PARTS:
            raise BonesimError(f"unknown phantom part {name!r}; the phantom paints "
                               f"{list(_phantom.PARTS)}", path, where)
        if "display_color" in tab:
            display, source = _rgb(tab, "display_color", path, where), "manifest"
        elif color is not None and fmt == "label-stack":
            display, source = color, "label"
        elif seg_default is not None:
            display, source = tuple(seg_default), "segment"
        else:
            display = tuple(cls.colors[0]) if cls is not None else \
                tuple(table.kind_colors[kind][0])
            source = "palette"
        monitor = tab.get("monitor", kind != "bone" and cls is not None and cls.monitor)
        if not isinstance(monitor, bool):
            raise BonesimError(f"'monitor' must be true or false, got {monitor!r}",
                               path, where)
        if monitor and kind == "bone":
            raise BonesimError("'monitor' = true on a structure of kind 'bone'; the "
                               "nerve monitor watches nerves (kind 'critical' or "
                               "'soft')", path, where)
        out.append(Structure(name, kind, label, color, display, monitor, source,
                             anatomy, segment))
    if not any(s.kind == "bone" for s in out):
        if from_file:
            raise BonesimError(
                f"no segment of {seg_path.name} reads as bone (segments: "
                f"{', '.join(repr(s.name) for s in out)}); add [[structures]] naming "
                "the bone segment with kind = \"bone\"", path, "structures")
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
                      and math.isfinite(v) for c in box for v in c))
        if not ok:
            raise BonesimError("'box_mm' must be [[xmin, ymin, zmin], [xmax, ymax, "
                               f"zmax]], got {box!r}", path, where)
        lo, hi = (tuple(float(v) for v in c) for c in box)
        if any(a >= b for a, b in zip(lo, hi)):
            raise BonesimError(f"'box_mm' min {list(lo)} must be below max {list(hi)} "
                               "on every axis", path, where)
    return Target(desc, tuple(structs), lo, hi)


def parse_manifest(path: str | Path) -> Case:
    """Parse and check one ``case.toml`` (no volume is read; a segmentation's
    header is, for its segment table)."""
    path = Path(path).resolve()
    doc = read_toml(path)
    check_keys(doc, _TOP_KEYS, path, "top level", required=("case", "volume"))
    case = doc["case"]
    check_keys(case, _CASE_KEYS, path, "case", required=("name", "side"))
    name = get_str(case, "name", path, "case")
    if not name.strip():
        raise BonesimError("'name' must not be empty", path, "case")
    desc = get_str(case, "description", path, "case", default="")
    side = get_str(case, "side", path, "case", choices=SIDES)
    volume = _parse_volume(doc["volume"], path)
    if "structures" not in doc and volume.segmentation is None:
        raise BonesimError("missing required key(s) 'structures' (only a 3D Slicer "
                           "segmentation brings its own)", path, "top level")
    structures = _parse_structures(doc.get("structures"), path, volume)
    camera = _parse_camera(doc["camera"], path) if "camera" in doc else None
    target = (_parse_target(doc["target"], path, [s.name for s in structures])
              if "target" in doc else None)
    case = Case(name, desc, side, path, volume, structures, camera, target)
    if "fragments" in doc:
        case = dataclasses.replace(case, fragments=_parse_fragments(doc["fragments"], path))
    if "physics" in doc:
        case = dataclasses.replace(case, gravity=_parse_physics(doc["physics"], path))
    return case


def _parse_fragments(tab, path: Path) -> Fragments:
    """``[fragments]``: ``speck_voxels``, a positive integer (parts cut off
    with fewer voxels become dust)."""
    where = "fragments"
    if not isinstance(tab, dict):
        raise BonesimError("'fragments' must be a table", path, "top level")
    check_keys(tab, _FRAGMENTS_KEYS, path, where)
    n = get_number(tab, "speck_voxels", path, where, default=Fragments.speck_voxels,
                   minimum=1, integer=True)
    return Fragments(int(n))


def _parse_physics(tab, path: Path):
    """``[physics] gravity = [x, y, z]``: a finite non-zero direction, case
    frame (its length does not matter). Returns the tuple, or None."""
    where = "physics"
    check_keys(tab, ("gravity",), path, where)
    if "gravity" not in tab:
        return None
    g = np.array(get_vector(tab, "gravity", path, where), dtype=float)
    if not np.all(np.isfinite(g)) or not np.linalg.norm(g) > 0:
        raise BonesimError(f"'gravity' must be a finite non-zero direction, got "
                           f"{g.tolist()}", path, where)
    return tuple(float(v) for v in g)
