"""A case carried inside a session file: the header's ``model`` record, which
with the stored tissue (:mod:`bonesim.io.embedded`) rebuilds the model a run
was recorded on, with no case, burr or material file present.

The record holds the case's name, side, structures (kinds, colours, monitor
flags), camera, target, fragments and gravity, the engine voxel, the burr
table with every value and the materials per kind (with the header's
oversampling, device limits and rate). :func:`case_record` and friends make
it from a loaded model; :func:`embedded_case` turns it back into a
:class:`~bonesim.io.case_records.Case` whose volume the session file holds,
so :func:`bonesim.io.loading.load_model` builds the same model as at
recording time (the recorded model hashes check it).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.io.case_records import Camera, Case, Fragments, Structure, Target, VolumeSpec
from bonesim.io.embedded import SESSION_FORMAT

__all__ = ["case_record", "burr_record", "burr_from_record", "materials_record",
           "materials_from_record", "embedded_case"]


def _floats(v) -> list | None:
    return None if v is None else [float(x) for x in v]


def case_record(case, voxel_mm: float) -> dict:
    """The JSON-ready record of a loaded, resolved case (``case.resolved(vol)``,
    as :attr:`Model.case <bonesim.engine.model.Model>` holds it): what
    :func:`embedded_case` rebuilds it from, with the arrays :func:`write_volume`
    stores; ``voxel_mm`` is the engine grid's voxel edge [mm].

    The camera stored is the one the run used (declared or derived), and the
    display colours are the settled ones, so a later version that derives
    views or colours differently shows the recording as it was recorded.
    """
    cam = case.camera
    t = case.target
    return {
        "name": case.name, "description": case.description, "side": case.side,
        "structures": [{"name": s.name, "kind": s.kind, "label": s.label,
                        "color": None if s.color is None else [int(c) for c in s.color],
                        "display_color": [int(c) for c in s.display_color],
                        "monitor": bool(s.monitor), "anatomy": s.anatomy,
                        "segment": s.segment} for s in case.structures],
        "camera": {"eye_mm": _floats(cam.eye_mm), "focal_mm": _floats(cam.focal_mm),
                   "up": _floats(cam.up), "source": case.camera_source},
        "target": None if t is None else {
            "description": t.description, "structures": list(t.structures),
            "box_min_mm": _floats(t.box_min_mm), "box_max_mm": _floats(t.box_max_mm)},
        "fragments": {"speck_voxels": int(case.fragments.speck_voxels)},
        "gravity": _floats(case.gravity),
        "source": {"format": case.volume.format, "voxel_mm": case.volume.voxel_mm},
        "voxel_mm": float(voxel_mm),
    }


def burr_record(burr) -> dict:
    """A burr's resolved values (:class:`bonesim.io.burrs.Burr`) as JSON-ready
    data; ``source`` becomes a string (the file it came from, or None)."""
    d = dataclasses.asdict(burr)
    d["source"] = None if burr.source is None else str(burr.source)
    return d


def burr_from_record(d: dict, where: str):
    """The :class:`~bonesim.io.burrs.Burr` of a :func:`burr_record`; pairs stored
    as lists become tuples again. ``where`` names the record in errors."""
    from bonesim.io.burrs import Burr

    names = {f.name: f for f in dataclasses.fields(Burr)}
    unknown = sorted(set(d) - set(names))
    if unknown:
        raise BonesimError(f"{where}: unknown burr field(s) {unknown}")
    kw = {}
    for k, v in d.items():
        if isinstance(v, list):
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kw[k] = v
    try:
        return Burr(**kw)
    except TypeError as exc:
        raise BonesimError(f"{where}: the burr record is incomplete ({exc})") from None


def materials_record(model) -> dict:
    """The material of each structure kind the model uses, read from the
    model's per-label arrays (exactly what the physics ran with):
    ``{kind: {"stiffness", "removal", "injury"}}``."""
    out = {}
    for s, st in enumerate(model.structures, start=1):
        out.setdefault(st.kind, {"stiffness": float(model.stiff[s]),
                                 "removal": float(model.removal[s]),
                                 "injury": bool(model.injury[s])})
    return out


def materials_from_record(rec: dict) -> dict:
    """The ``materials`` argument of :func:`bonesim.io.loading.load_model` for a
    :func:`materials_record`."""
    from bonesim.engine.materials import Material

    return {k: Material(k, float(v["stiffness"]), float(v["removal"]), bool(v["injury"]))
            for k, v in rec.items()}


def embedded_case(path, record: dict, volume=None):
    """The :class:`~bonesim.io.case_records.Case` a session file carries: its
    ``manifest`` is the session file, its volume (format
    :data:`SESSION_FORMAT`) the file's ``/model`` arrays. Colours and camera
    are the recorded ones (``color_source`` ``"manifest"``: never re-settled).
    ``volume``: the file's tissue, already read (:func:`bonesim.io.embedded.read_volume`),
    handed to the case so that it is not read again."""
    path = Path(path).resolve()
    try:
        voxel_mm = float(record["voxel_mm"])
        structs = tuple(Structure(
            name=s["name"], kind=s["kind"], label=s["label"],
            color=None if s["color"] is None else tuple(s["color"]),
            display_color=tuple(s["display_color"]), monitor=bool(s["monitor"]),
            color_source="manifest", anatomy=s["anatomy"], segment=s["segment"])
            for s in record["structures"])
        cam = record["camera"]
        t = record["target"]
        target = None if t is None else Target(
            t["description"], tuple(t["structures"]),
            None if t["box_min_mm"] is None else tuple(t["box_min_mm"]),
            None if t["box_max_mm"] is None else tuple(t["box_max_mm"]))
        grav = record["gravity"]
        case = Case(
            name=record["name"], description=record["description"], side=record["side"],
            manifest=path,
            volume=VolumeSpec(format=SESSION_FORMAT, path=path, voxel_mm=voxel_mm),
            structures=structs,
            declared_camera=Camera(tuple(cam["eye_mm"]), tuple(cam["focal_mm"]),
                                   tuple(cam["up"])),
            target=target, fragments=Fragments(int(record["fragments"]["speck_voxels"])),
            gravity=None if grav is None else tuple(grav))
    except (KeyError, TypeError, ValueError) as exc:
        raise BonesimError(f"{path}: the header's model record is incomplete "
                           f"({type(exc).__name__}: {exc})") from None
    if volume is not None:
        case.hand_over(volume)
    return case
