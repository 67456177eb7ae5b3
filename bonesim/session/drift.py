"""What differs between the files a session was recorded on and today's
(``bonesim sessions info --against-current``).

A schema 4 file carries its model (:mod:`bonesim.io.embedded`), so it plays
back, replays and scores whatever happened to the case, burr and material
files since. This module says what did happen: for the case, each burr, the
materials and the model as a whole, whether today's files give the same
thing, differ, or are gone, and which bonesim and schema wrote the file.
"""
from __future__ import annotations

import json

from bonesim.errors import BonesimError

__all__ = ["against_current"]


def _today_case(session):
    """Today's case for a recording (:meth:`Session.case_source
    <bonesim.session.reader.Session.case_source>`), or the reason there is
    none."""
    from bonesim.io.case import load_case

    h = session.header
    try:
        case = load_case(session.case_source())
    except BonesimError as exc:
        return None, str(exc)
    if h.get("voxel_mm") is not None:
        case = case.with_voxel_mm(float(h["voxel_mm"]))
    return case, None


def _item(what: str, status: str, detail: str = "") -> dict:
    return {"what": what, "status": status, "detail": detail}


def against_current(session) -> dict:
    """Compare a session's recorded case, burrs, materials and model with what
    today's files give.

    Returns
    -------
    dict
        ``items``: one ``{"what", "status", "detail"}`` per compared thing,
        status ``"same"``, ``"differs"`` or ``"missing"`` (today has no such
        file); ``differs``: how many are not the same; ``recorded_version``
        and ``current_version`` (bonesim), ``schema``; ``self_contained``:
        the file rebuilds its model on its own (then differences do not stop
        it from playing back, replaying and scoring).
    """
    from bonesim import __version__
    from bonesim.engine.materials import load_materials
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import load_model
    from bonesim.session.header import burr_sha256, case_sha256, model_sha256

    h = session.header
    items = []
    case, why = _today_case(session)
    if case is None:
        items.append(_item(f"case {h['case']['name']}", "missing", why))
    else:
        now = case_sha256(case)
        same = now == h["case"].get("sha256")
        items.append(_item(f"case {h['case']['name']}", "same" if same else "differs",
                           "" if same else f"today's {case.manifest} and the volume it "
                           "names hash differently"))
    burrs = []
    for q, b in enumerate(h["burrs"]):
        try:
            today = load_burr(b["name"])
        except BonesimError as exc:
            items.append(_item(f"burr {q} {b['name']}", "missing", str(exc)))
            burrs.append(None)
            continue
        burrs.append(today)
        same = burr_sha256(today) == b.get("sha256")
        items.append(_item(f"burr {q} {b['name']}", "same" if same else "differs",
                           "" if same else _burr_diff(h, q, today)))
    rec = h.get("model", {}).get("materials")
    if rec is not None:
        try:
            mats = load_materials()
        except BonesimError as exc:
            items.append(_item("materials", "missing", str(exc)))
        else:
            diff = [f"{k}: {v} recorded, {_mat(mats.get(k))} today" for k, v in rec.items()
                    if _mat(mats.get(k)) != v]
            items.append(_item("materials", "differs" if diff else "same", "; ".join(diff)))
    if case is not None and None not in burrs:
        try:
            m = load_model(case, burrs[0], device=session.device_caps(),
                           oversample=int(h["oversample"]))
            got = [model_sha256(mm) for mm in [m] + [m.with_burr(b) for b in burrs[1:]]]
        except (BonesimError, ValueError) as exc:
            items.append(_item("model", "missing", f"today's files build no model ({exc})"))
        else:
            same = got == list(h["model_sha256"])
            items.append(_item("model", "same" if same else "differs",
                               "" if same else "today's files build other physics "
                               "(grid, materials or burr samples)"))
    return {"items": items, "differs": sum(i["status"] != "same" for i in items),
            "recorded_version": h.get("bonesim_version"), "current_version": __version__,
            "schema": session.schema, "self_contained": session.carries_model}


def _mat(m) -> dict | None:
    return None if m is None else {"stiffness": float(m.stiffness),
                                   "removal": float(m.removal), "injury": bool(m.injury)}


def _burr_diff(h: dict, q: int, today) -> str:
    """The burr values that changed, when the file carries the recorded ones."""
    from bonesim.io.embedded_case import burr_record

    recs = h.get("model", {}).get("burrs")
    if not recs or q >= len(recs):
        return "today's burr file resolves to other values"
    now = json.loads(json.dumps(burr_record(today)))
    was = recs[q]
    keys = [k for k in sorted(set(now) | set(was)) if k != "source" and now.get(k) != was.get(k)]
    return ", ".join(f"{k} {was.get(k)} -> {now.get(k)}" for k in keys[:8]) or \
        "today's burr file resolves to other values"
