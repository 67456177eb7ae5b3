"""The final product, item by item: a mastoidectomy scored as assessors score it.

Published final-product scales for mastoidectomy (the Welling scale and its
modified versions; ``../shared/MASTOIDECTOMY.md``) ask, item by item, whether
the cavity is saucerized without overhangs, the tegmen and the sinus thinned
without exposure, the sinodural angle opened, the posterior canal wall
thinned and intact, the antrum opened, the lateral canal and the incus
identified, the mastoid tip cleared, and the facial nerve, chorda, sinus,
dura and labyrinth unharmed. This module scores each item 0 (absent), 1
(partial) or 2 (complete) from the tissue at the end of a run, the case's
structures and its landmarks (:mod:`bonesim.io.landmarks`), with the
measurement behind each score.

The items, their measurements, thresholds and the one sentence of advice per
outcome are data: ``bonesim/data/assessment.toml``
(:mod:`metrics.assessment_items`); the measurements are
:mod:`metrics.assessment_measure`'s; ``docs/assessment.md`` explains both.

Entry points
------------
:func:`assess_tissue`
    From arrays: the labels at the start, the voxels left at the end.
:func:`assess_grid`
    From a model and a final grid (the headless main job's state, the
    window's replica).
:func:`assess_session`
    From a recorded run alone: its case is rebuilt, the removals of its last
    epoch taken away.
:func:`assessment_row`
    One flat row per run for the cohort table (``assess_total``,
    ``assess_<item>``...); :func:`assessment_progress` those rows over a
    resident's sessions, in order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from metrics import assessment_measure as M
from metrics.assessment_items import Scale, load_scale

__all__ = ["ItemResult", "Assessment", "assess_tissue", "assess_grid", "assess_session",
           "cohort_row", "cohort_columns",
           "final_present", "assessment_row", "assessment_columns", "assessment_progress",
           "checklist", "structure_masks", "ROW_PREFIX"]

#: Prefix of the cohort table's assessment columns.
ROW_PREFIX = "assess_"
#: Most voxels kept per item for the picture.
_MAX_REGION = 4000
#: Units and words of the quantities in the checklist.
_WORDS = {"overhang_mm3": ("overhang", "{:.0f} mm^3"),
          "hidden_wall_share": ("wall hidden", "{:.0%}"),
          "thinnest_mm": ("thinnest bone", "{:.1f} mm"),
          "exposed_mm2": ("exposed", "{:.1f} mm^2"),
          "gap_mm": ("bone left", "{:.1f} mm"),
          "opening_mm2": ("opening", "{:.0f} mm^2"),
          "removed_mm3": ("drilled", "{:.1f} mm^3")}


@dataclass(frozen=True)
class ItemResult:
    """One item's score.

    Attributes
    ----------
    name, title : str
    score : int or None
        0, 1 or 2; None when not applicable.
    outcome : str
        ``"done"``, ``"partial"``, ``"missed"``, ``"violated"`` or ``"n/a"``.
    quantities : dict of str -> float
        The measurement behind the score (units in the names: ``_mm``,
        ``_mm2``, ``_mm3``; shares in [0, 1]); inf where nothing came near.
    advice : str
        One sentence for next time ("" when not applicable).
    why : str
        Why the item does not apply ("" when it does).
    region_mm : (n, 3) float
        Voxel centres of the item's region for the picture, case frame [mm].
    anchor_mm : (3,) float or None
        Where the item's label goes in the picture.
    """

    name: str
    title: str
    score: int | None
    outcome: str
    quantities: dict
    advice: str
    why: str = ""
    region_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    anchor_mm: np.ndarray | None = field(default=None, repr=False)

    def measured(self) -> str:
        """The quantities behind the score, in words."""
        parts = []
        for k, (word, fmt) in _WORDS.items():
            if k in self.quantities:
                v = self.quantities[k]
                parts.append(f"{word} " + ("none near" if v is None or not math.isfinite(v)
                                           else fmt.format(v)))
        return ", ".join(parts)


@dataclass(frozen=True)
class Assessment:
    """A run's final product, item by item.

    Attributes
    ----------
    items : tuple of ItemResult
        In the scale's order.
    case : str
    voxel_mm : float
    removed_mm3 : float
        Tissue removed [mm^3].
    """

    items: tuple
    case: str = ""
    voxel_mm: float = 0.0
    removed_mm3: float = 0.0

    @property
    def total(self) -> int:
        return int(sum(it.score for it in self.items if it.score is not None))

    @property
    def max_total(self) -> int:
        return 2 * sum(1 for it in self.items if it.score is not None)

    def item(self, name: str) -> ItemResult:
        for it in self.items:
            if it.name == name:
                return it
        raise KeyError(name)

    def scores(self) -> dict:
        """``{item: score or None}``."""
        return {it.name: it.score for it in self.items}

    def as_dict(self) -> dict:
        """JSON-ready (non-finite quantities as None)."""
        def clean(v):
            v = float(v)
            return v if math.isfinite(v) else None
        return {"case": self.case, "voxel_mm": self.voxel_mm,
                "removed_mm3": round(self.removed_mm3, 3),
                "total": self.total, "max_total": self.max_total,
                "items": [{"name": it.name, "title": it.title, "score": it.score,
                           "max": None if it.score is None else 2, "outcome": it.outcome,
                           "quantities": {k: clean(v) for k, v in it.quantities.items()},
                           "advice": it.advice, **({"why": it.why} if it.why else {})}
                          for it in self.items]}


def checklist(a: Assessment) -> list[str]:
    """The resident's checklist: a title line, then per item its score, the
    measurement and one sentence for next time."""
    n_na = sum(1 for it in a.items if it.score is None)
    out = [f"final product: {a.total} of {a.max_total} "
           f"({len(a.items) - n_na} items scored" + (f", {n_na} not applicable" if n_na
                                                     else "") + ")"]
    for it in a.items:
        if it.score is None:
            out.append(f"  [n/a]  {it.title}: {it.why}")
            continue
        tag = f"[{it.score}/2]" + (" violated" if it.outcome == "violated" else "")
        out.append(f"  {tag:6s} {it.title} ({it.measured()}). {it.advice}")
    return out


# ------------------------------------------------------------------ groups
def _lm_lookup(landmarks, name, centres_mm) -> np.ndarray:
    """Whether each point falls in the landmark group mask ``name``."""
    m = landmarks.masks.get(name)
    if m is None or not len(centres_mm):
        return np.zeros(len(centres_mm), bool)
    h, o = landmarks.cortex["h"], np.asarray(landmarks.cortex["origin_mm"], float)
    q = np.rint((centres_mm - o) / h).astype(np.int64)
    ok = np.all((q >= 0) & (q < m.shape), axis=1)
    out = np.zeros(len(q), bool)
    out[ok] = m[tuple(q[ok].T)]
    return out


def _groups(box, structures, landmarks, params) -> tuple[dict, set]:
    """The structure groups in the box (:class:`metrics.assessment_measure.Box`)
    and the groups the case has at all."""
    from bonesim.io.anatomy import classify
    from bonesim.io.landmarks import structure_groups

    groups = structure_groups(structures)
    out: dict = {}
    has: set = set()

    def add(g, m):
        has.add(g)
        if m.any():
            out[g] = out[g] | m if g in out else m

    for s, (st, g) in enumerate(zip(structures, groups), start=1):
        if st.kind == "bone":
            continue
        m = box.labels == s
        cls = classify(st.name)
        cid = cls.id if cls is not None else (getattr(st, "anatomy", "") or "")
        if cid == "chorda_tympani":
            add("chorda_tympani", m)
        if cid in ("incus", "ossicles"):
            add("incus", m)
        for g1 in ("facial_nerve", "labyrinth", "ear_canal"):
            if g1 in g:
                add(g1, m)
        thin = g & {"sinus", "tegmen", "dura"}
        if not thin:
            continue
        ijk = np.argwhere(m)
        c = box.centres(ijk)
        in_s, in_t = _lm_lookup(landmarks, "sinus", c), _lm_lookup(landmarks, "tegmen", c)
        in_d = _lm_lookup(landmarks, "dura", c)
        none = ~(in_s | in_t | in_d)
        own = "sinus" if "sinus" in thin and len(thin) == 1 else \
            "tegmen" if "tegmen" in thin else "dura"
        pick = {"sinus": in_s | (none & (own == "sinus")),
                "tegmen": ~in_s & (in_t | (none & (own == "tegmen")))}
        pick["dura"] = ~pick["sinus"] & ~pick["tegmen"]
        for g1, sel in pick.items():
            mm = np.zeros(m.shape, bool)
            mm[tuple(ijk[sel].T)] = True
            if sel.any() or g1 == own:
                add(g1, mm)
    for g1 in ("sinus", "tegmen", "dura"):      # split from a merged label elsewhere
        if g1 in landmarks.masks:
            has.add(g1)
    teg = landmarks.get("tegmen")
    if "tegmen" not in landmarks.masks and "dura" in has and teg is not None \
            and teg.confidence != "estimated":
        # dura without a tegmen of its own: the tegmen is the dura at and above
        # the lowest dura over the mastoid (the landmark's height)
        has.add("tegmen")
        if "dura" in out:
            z = box.origin_mm[2] + box.h * np.arange(box.labels.shape[2])
            up = (z >= teg.point_mm[2] - box.h / 2)[None, None, :]
            out["tegmen"] = out["dura"] & up
            out["dura"] = out["dura"] & ~up
    if "ear_canal" not in out:
        lumen = _canal_lumen(box, landmarks, params)
        if lumen is not None:
            out["ear_canal"] = lumen
            has.add("ear_canal")
    return out, has


def _canal_lumen(box, landmarks, params):
    """The ear canal's air (module [measure] notes) when it is not labelled."""
    lm = landmarks.get("ear_canal")
    if lm is None:
        return None
    lat = landmarks.lateral
    p0 = np.asarray(lm.point_mm, float)
    r = float(lm.detail.get("radius_mm", 4.0)) + params["canal_radius_extra_mm"]
    # the canal ends where its axis first meets tissue (the drum, the ossicles,
    # bone), at most canal_length_mm in
    depth = params["canal_length_mm"]
    ts = np.arange(params["canal_skip_mm"], depth, box.h / 2.0)
    q = box.index_of(p0[None, :] - np.outer(ts, lat))
    ok = np.all((q >= 0) & (q < box.tissue0.shape), axis=1)
    hit = np.zeros(len(ts), bool)
    hit[ok] = box.tissue0[tuple(q[ok].T)]
    if hit.any():
        depth = float(ts[np.argmax(hit)])
    ijk = np.argwhere(~box.tissue0)
    c = box.centres(ijk)
    s = (c - p0) @ lat                          # lateral coordinate from the opening
    off = c - p0 - np.outer(s, lat)
    ok = (np.einsum("ij,ij->i", off, off) <= r * r) & (s <= -params["canal_skip_mm"]) \
        & (s >= -depth)
    out = np.zeros(box.tissue0.shape, bool)
    out[tuple(ijk[ok].T)] = True
    return out


# ------------------------------------------------------------------ assess
def _region(box, ijk, limit=_MAX_REGION):
    ijk = np.asarray(ijk).reshape(-1, 3)
    if len(ijk) > limit:
        ijk = ijk[np.linspace(0, len(ijk) - 1, limit).astype(int)]
    return box.centres(ijk)


def _measure(item, box, lm, params, has):
    """``(quantities, region_ijk, anchor_mm, why)`` of one item."""
    g = box.groups
    t = item.target
    if item.measure == "sightlines":
        q = M.sightlines(box, params["_eye"], params)
        reg = np.concatenate([q.pop("_overhang"), q.pop("_hidden")])
        anchor = box.centres(reg.mean(0)) if len(reg) else \
            box.centres(np.argwhere(box.removed).mean(0)) if box.removed.any() else None
        return q, reg, anchor, ""
    if item.measure == "cover":
        if t == "lateral_canal":
            p = lm.point("lateral_canal")
            if p is None or "labyrinth" not in has:
                return None, None, None, "no lateral canal found (no labyrinth label)"
            lab = g.get("labyrinth", np.zeros(box.present.shape, bool))
            surf = M.surface_of(box, lab) & M.ball_mask(box, p, params["lateral_canal_near_mm"])
        else:
            if t not in has:
                return None, None, None, f"the case has no {t.replace('_', ' ')}"
            if t == "ear_canal" and lm.get("ear_canal") is None:
                return None, None, None, "no ear canal found"
            mask = g.get(t, np.zeros(box.present.shape, bool))
            if t == "ear_canal":         # the lumen's wall: air or canal next to bone
                surf = mask & M.face_adjacent(box.bone0)
            else:
                surf = M.surface_of(box, mask)
            p = lm.point({"sinus": "sigmoid_sinus"}.get(t, t))
        crit = {c.quantity: c for c in item.criteria}.get("thinnest_mm")
        thin = crit.partial if crit is not None else 1.0
        q = M.cover_quantities(box, surf, params, thin, drilled_only=item.against == "drilled")
        cov, ijk = q.pop("_cover"), q.pop("_ijk")
        show = cov <= max(thin, q["thinnest_mm"] + 0.5 if math.isfinite(q["thinnest_mm"])
                          else -1.0)
        reg = ijk[show]
        anchor = box.centres(reg.mean(0)) if len(reg) else p
        return q, reg, anchor, ""
    if item.measure == "antrum":
        a = lm.get("antrum")
        if a is None:
            return None, None, None, "no antrum found or estimated"
        region = M.antrum_region(box, a.point_mm, float(a.detail.get("radius_mm", 0.0)),
                                 a.confidence != "estimated", params)
        q = M.antrum_quantities(box, region)
        return q, np.argwhere(region), np.asarray(a.point_mm, float), ""
    if item.measure == "angle":
        if lm.get("sinodural_angle") is None or not {"sinus", "tegmen"} <= has:
            return None, None, None, "needs both the sigmoid sinus and the tegmen"
        q = M.angle_gap(box)
        at = q.pop("_at")
        if at is None:
            return q, np.zeros((0, 3), int), lm.point("sinodural_angle"), ""
        rem = np.argwhere(box.removed)
        near = rem[np.linalg.norm(rem - at, axis=1) * box.h <= 2.0]
        return q, near, box.centres(at), ""
    if item.measure == "reach":
        if t not in has:
            return None, None, None, f"the case has no {t.replace('_', ' ')} label"
        tgt = g.get(t)
        q = M.reach_gap(box, tgt)
        reg = np.argwhere(tgt) if tgt is not None else np.zeros((0, 3), int)
        anchor = box.centres(reg.mean(0)) if len(reg) else None
        return q, reg, anchor, ""
    if item.measure == "tip":
        tip = lm.get("mastoid_tip")
        if tip is None:
            return None, None, None, "no mastoid tip found"
        q = M.tip_gap(box, tip.point_mm[2])
        at = q.pop("_at")
        reg = np.zeros((0, 3), int)
        if at is not None:
            rem = np.argwhere(box.removed & box.bone0)
            reg = rem[np.linalg.norm(rem - at, axis=1) * box.h <= 2.5]
        return q, reg, np.asarray(tip.point_mm, float), ""
    if item.measure == "injury":
        names = ("tegmen", "dura") if t == "dura" else (t,)
        if not any(n in has for n in names):
            return None, None, None, f"the case has no {t.replace('_', ' ')}"
        mask = np.zeros(box.present.shape, bool)
        for n in names:
            if n in g:
                mask |= g[n]
        q = M.injury_quantities(box, mask, show_exposed=any(
            c.quantity == "exposed_mm2" for c in item.criteria))
        reg = q.pop("_ijk")
        anchor = box.centres(reg.mean(0)) if len(reg) else None
        return q, reg, anchor, ""
    raise ValueError(f"unknown measure {item.measure!r}")


def assess_tissue(labels0, present, spacing_mm: float, origin_mm, structures, landmarks,
                  eye_mm, *, density0=None, scale: Scale | None = None,
                  case: str = "") -> Assessment:
    """Score a final product from arrays.

    Parameters
    ----------
    labels0 : (nx, ny, nz) uint8
        Structure index per voxel at the start (``s >= 1`` is
        ``structures[s - 1]``), axes x, y, z of the case frame.
    present : (nx, ny, nz) bool
        Voxels with tissue left at the end.
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``name`` and ``kind``.
    landmarks : bonesim.io.landmarks.Landmarks
        The case's (``case.landmarks``).
    eye_mm : (3,) float
        The surgeon's eye (the case camera's) [mm].
    density0 : (nx, ny, nz) float, optional
        Density at the start (tissue where > 0; default: every labelled voxel).
    scale : Scale, optional
        Default :func:`metrics.assessment_items.load_scale`.
    case : str
        The case's name, for the record.

    Returns
    -------
    Assessment

    Raises
    ------
    ValueError
        On arrays of different shapes or a non-positive spacing.
    """
    scale = load_scale() if scale is None else scale
    labels0 = np.asarray(labels0)
    present = np.asarray(present, bool)
    if labels0.ndim != 3 or present.shape != labels0.shape:
        raise ValueError(f"labels0 {labels0.shape} and present {present.shape} must be "
                         "3-D arrays of one shape")
    h = float(spacing_mm)
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"spacing_mm must be a positive number, got {spacing_mm!r}")
    origin = np.asarray(origin_mm, float).reshape(3)
    tissue0 = labels0 > 0 if density0 is None else (labels0 > 0) & (np.asarray(density0) > 0)
    present = present & tissue0
    params = dict(scale.measure)
    params["_eye"] = np.asarray(eye_mm, float).reshape(3)
    bounds = M.make_box(np.where(tissue0, labels0, 0), present, h, origin,
                        params["box_pad_mm"])
    lo, hi = bounds if bounds is not None else (np.zeros(3, int), np.ones(3, int))
    sl = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    is_bone = np.array([False] + [s.kind == "bone" for s in structures])
    lab = labels0[sl]
    box = M.Box(lo=np.asarray(lo), h=h, origin_mm=origin + h * np.asarray(lo), labels=lab,
                tissue0=tissue0[sl], present=present[sl],
                removed=tissue0[sl] & ~present[sl],
                bone0=tissue0[sl] & is_bone[np.minimum(lab, len(is_bone) - 1)])
    groups, has = _groups(box, structures, landmarks, params)
    box.groups = groups
    box.occluder = M.occluder(box, params)
    box.cavity = box.removed | M.opened_air(box, params["hull_mm"], params["opened_reach_mm"],
                                            params["_eye"], params["step_voxels"])
    results = []
    for item in scale.items:
        q, reg, anchor, why = _measure(item, box, landmarks, params, has)
        if q is None:
            results.append(ItemResult(item.name, item.title, None, "n/a", {}, "", why))
            continue
        s, outcome = item.score(q)
        results.append(ItemResult(item.name, item.title, s, outcome,
                                   {k: float(v) for k, v in q.items()},
                                   item.advice[outcome], "", _region(box, reg),
                                   None if anchor is None else np.asarray(anchor, float)))
    removed = float(np.count_nonzero(box.removed) * h ** 3) if bounds is not None else 0.0
    return Assessment(tuple(results), case, h, removed)


def structure_masks(labels0, spacing_mm: float, origin_mm, structures, landmarks, *,
                    scale: Scale | None = None) -> dict:
    """The structure groups the assessment measures on, over the whole grid:
    ``sinus``, ``tegmen``, ``dura`` (merged labels split as the landmarks
    split them), ``facial_nerve``, ``chorda_tympani``, ``labyrinth``,
    ``incus`` and ``ear_canal`` (the canal's lumen: its label, else the air
    of the canal found in the cortex), those the case has; (nx, ny, nz) bool."""
    scale = load_scale() if scale is None else scale
    labels0 = np.asarray(labels0)
    t0 = labels0 > 0
    is_bone = np.array([False] + [s.kind == "bone" for s in structures])
    box = M.Box(lo=np.zeros(3, int), h=float(spacing_mm),
                origin_mm=np.asarray(origin_mm, float).reshape(3), labels=labels0,
                tissue0=t0, present=t0, removed=np.zeros_like(t0),
                bone0=t0 & is_bone[labels0])
    return _groups(box, structures, landmarks, dict(scale.measure))[0]


def assess_grid(model, grid, *, scale: Scale | None = None) -> Assessment:
    """Score the tissue of ``grid`` (a state's or replica's, at the end of a
    run) against ``model``'s initial tissue; the landmarks and the eye are
    its case's.

    Raises
    ------
    ValueError
        When the model has no case (built from arrays: no landmarks).
    """
    case = getattr(model, "case", None)
    if case is None:
        raise ValueError("the model has no case: no landmarks to assess against")
    d0, lab0 = model.grid.to_dense()
    d1, _ = grid.to_dense()
    return assess_tissue(lab0, d1 > 0, model.spacing_mm, model.grid.origin_mm,
                         model.structures, case.landmarks, case.camera.eye_mm,
                         density0=d0, scale=scale, case=model.name)


def final_present(session, model) -> np.ndarray:
    """(nx, ny, nz) bool: the tissue left at the end of a recorded run: the
    model's initial tissue less every voxel removed in the last epoch
    (drilled or shed as dust; :func:`metrics.regions.final_epoch`)."""
    from metrics.regions import final_epoch

    d0, _ = model.grid.to_dense()
    present = d0 > 0
    rem = session.removals
    last = final_epoch(session)
    ijk = np.asarray(rem["ijk"])[np.asarray(rem["epoch"]) == last].astype(np.int64)
    if len(ijk):
        ok = np.all((ijk >= 0) & (ijk < present.shape), axis=1)
        present[tuple(ijk[ok].T)] = False
    return present


def assess_session(session, *, model=None, scale: Scale | None = None) -> Assessment:
    """Score a recorded run from the session alone (module docstring).

    Parameters
    ----------
    session : Session or path
    model : Model, optional
        Default ``session.load_model()``.
    scale : Scale, optional
    """
    from bonesim.session.reader import read_session

    s = read_session(session) if not hasattr(session, "header") else session
    model = s.load_model() if model is None else model
    d0, lab0 = model.grid.to_dense()
    case = model.case
    return assess_tissue(lab0, final_present(s, model), model.spacing_mm,
                         model.grid.origin_mm, model.structures, case.landmarks,
                         case.camera.eye_mm, density0=d0, scale=scale, case=model.name)


def assessment_columns(scale: Scale | None = None, prefix: str = ROW_PREFIX) -> tuple:
    """The columns :func:`assessment_row` fills, in order (for a table's
    schema: ``assess_total``, ``assess_max``, ``assess_share``, then one per
    item of the scale)."""
    scale = load_scale() if scale is None else scale
    return (f"{prefix}total", f"{prefix}max", f"{prefix}share") + \
        tuple(f"{prefix}{it.name}" for it in scale.items)


def assessment_row(assessment, prefix: str = ROW_PREFIX, *, model=None) -> dict:
    """One flat row of a run's assessment for the cohort table.

    The cohort's per-run scorer joins it to a run's metrics row (e.g. in
    :func:`metrics.cohort._score_file`: ``m.update(assessment_row(s,
    model=model))``, with :func:`assessment_columns` added to the table's
    columns).

    Parameters
    ----------
    assessment : Assessment, Session or path
        A session is assessed first (:func:`assess_session`).
    model : Model, optional
        The session's model, when the caller has rebuilt it already.

    Returns
    -------
    dict
        ``assess_total``, ``assess_max`` (int), ``assess_share`` (total /
        max, NaN when nothing applies) and ``assess_<item>`` (0, 1, 2; NaN
        when not applicable) per item of the scale.
    """
    a = assessment if isinstance(assessment, Assessment) else \
        assess_session(assessment, model=model)
    row = {f"{prefix}total": a.total, f"{prefix}max": a.max_total,
           f"{prefix}share": a.total / a.max_total if a.max_total else float("nan")}
    for it in a.items:
        row[f"{prefix}{it.name}"] = float("nan") if it.score is None else float(it.score)
    return row


def cohort_row(session, models, path) -> dict:
    """The cohort's per-run row provider (:data:`metrics.cohort.ROW_PROVIDERS`):
    :func:`assessment_row` of a session whose burr models the worker has
    rebuilt already (``models[0]``); ``path`` is not needed."""
    return assessment_row(session, model=models[0] if models else None)


def cohort_columns(scale: Scale | None = None) -> dict:
    """:func:`assessment_columns` as the cohort table's column record:
    ``column -> (unit, better)``; every item and the total are better higher."""
    units = {f"{ROW_PREFIX}total": "points", f"{ROW_PREFIX}max": "points",
             f"{ROW_PREFIX}share": ""}
    return {c: (units.get(c, "0-2"), 0 if c == f"{ROW_PREFIX}max" else +1)
            for c in assessment_columns(scale)}


def assessment_progress(sessions) -> list[dict]:
    """A resident's items over sessions: one :func:`assessment_row` per
    session file with ``file``, ``participant``, ``start_time`` and
    ``session`` (1, 2, ... per participant in order of start time), sorted by
    participant and start time; a file that cannot be read or assessed gives
    a row with ``error`` (one line).

    Parameters
    ----------
    sessions : iterable of path
    """
    from bonesim.session.reader import read_session

    rows = []
    for p in sessions:
        try:
            s = read_session(p)
            row = {"file": str(p), "participant": str(s.header.get("participant") or ""),
                   "start_time": str(s.header.get("start_time") or ""),
                   **assessment_row(assess_session(s))}
        except Exception as exc:            # one line per bad file, never a crash
            row = {"file": str(p), "participant": "", "start_time": "",
                   "error": " ".join(str(exc).split())}
        rows.append(row)
    rows.sort(key=lambda r: (r["participant"], r["start_time"], r["file"]))
    n: dict = {}
    for r in rows:
        n[r["participant"]] = n.get(r["participant"], 0) + 1
        r["session"] = n[r["participant"]]
    return rows
