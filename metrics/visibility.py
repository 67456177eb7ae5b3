"""Voxel visibility at removal, recomputed from a recording alone.

SPEC ("Metrics", voxel visibility): when a voxel is removed, the segment from
it to the eye is traced; if it passes through any bone voxel other than those
in contact with the drill, the removal was not visible (the trainee was
undercutting). The per-run visible fraction is the metric (reported to
correlate with instructor scores at R = 0.68), and a view colouring the
removed voxels visible / hidden shows where.

Offline recomputation
---------------------
:func:`recompute_visible` is a pure function of the session file: it rebuilds
the models from the recorded case and burrs (:meth:`Session.burr_models`),
takes the eye from the camera stream (before the first logged pose: the case
camera, as the recorder does), the burr centre and burr index of each
removal's step from the samples, and plays the tissue-event stream in order
(removals, resets, splits, poses) through the physics judge
(:class:`bonesim.physics.visibility.VisibilityTracker`, the very code the
recorder runs live; nothing of its kernel is copied here). All removals
between two other events are judged in one kernel call, so a run costs a
few Python calls per reset, split or pose, not per removal.

On a recorded run the recomputed verdicts equal the ``visible`` column the
recorder wrote, removal for removal (tests/metrics/test_visibility.py).
:attr:`VisibilityResult.live_mismatches` counts any disagreement. One way a
live recording could disagree (possible by the code, not seen in the
tests): the window's recorder stamps a camera pose with the loop time it
reads, and a pose stamped at or before a removal that reaches the writer
only after that removal was judged was not seen by the live judge; the
recomputation (which sees the whole camera stream) uses it.

Results
-------
:func:`visibility` gives a :class:`VisibilityResult`: the verdict of every
removal with its time, structure and case-frame centre [mm]; the visible
fraction overall, per structure (label of the removed voxel -> name), per
time window and cumulatively. :func:`render_visibility` draws the thesis'
picture offscreen to a PNG: removed voxels as small cubes, green when they
were visible, red when hidden, the bone itself not drawn, chosen structures
shown, the case camera, and the fractions as text.

Frames and units: positions in the case frame [mm]; times on the session's
clock [s] (``samples.t_s``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bonesim.engine import events
from bonesim.engine.bodies import to_case_frame
from bonesim.io.anatomy import clinical_name
from bonesim.render.visibility_view import (HIDDEN_RGB, VISIBLE_OPACITY, VISIBLE_RGB,
                                            visibility_scene)
from bonesim.render.visibility_view import show_visibility as show_visibility_window

__all__ = ["WINDOW_S", "VISIBLE_RGB", "HIDDEN_RGB", "VISIBLE_OPACITY", "StructureVisibility",
           "VisibilityResult", "recompute_visible", "visibility", "visible_fraction",
           "render_visibility", "show_visibility"]

#: Default length of the windows of the over-time fraction [s].
WINDOW_S = 5.0


@dataclass(frozen=True)
class StructureVisibility:
    """Removals of one structure.

    Attributes
    ----------
    label : int
        Structure label of the removed voxels.
    n_removed, n_visible : int
    fraction : float
        ``n_visible / n_removed`` (NaN when nothing was removed).
    """

    label: int
    n_removed: int
    n_visible: int
    fraction: float


@dataclass(frozen=True)
class VisibilityResult:
    """Voxel visibility of one run (:func:`visibility`).

    Attributes
    ----------
    t_s : (n,) float
        Time of each removal's step [s], session clock, in stream order.
    visible : (n,) int8
        Recomputed verdict: 1 visible, 0 hidden.
    recorded : (n,) int8
        The recorder's live verdict (1, 0, or -1 where unknown).
    label : (n,) uint8
        Structure label of each removed voxel.
    centre_mm : (n, 3) float
        Removed voxel's centre in the case frame [mm] (its body's pose at
        the removal applied).
    epoch : (n,) int
        Case resets before each removal.
    n_removed, n_visible : int
    fraction : float
        Visible fraction over the run (NaN when nothing was removed).
    by_structure : dict of str -> StructureVisibility
        Per structure name, the structures with removals only.
    window_s : float
        Window length [s].
    window_start_s : (m,) float
        Start of each window [s], session clock; window ``w`` covers
        ``[window_start_s[w], window_start_s[w] + window_s)`` (the last one
        also takes a removal exactly at its end).
    window_removed, window_visible : (m,) int
    window_fraction : (m,) float
        Visible fraction in each window (NaN for windows without removals).
    cumulative_fraction : (m,) float
        Visible fraction of all removals up to each window's end (NaN until
        the first removal).
    live_mismatches : int
        Removals whose known live verdict (``recorded`` != -1) differs from
        the recomputed one.
    """

    t_s: np.ndarray
    visible: np.ndarray
    recorded: np.ndarray
    label: np.ndarray
    centre_mm: np.ndarray
    epoch: np.ndarray
    n_removed: int
    n_visible: int
    fraction: float
    by_structure: dict
    window_s: float
    window_start_s: np.ndarray
    window_removed: np.ndarray
    window_visible: np.ndarray
    window_fraction: np.ndarray
    cumulative_fraction: np.ndarray
    live_mismatches: int
    names: dict = field(default_factory=dict, repr=False)

    @property
    def n_hidden(self) -> int:
        return self.n_removed - self.n_visible

    def summary(self) -> dict:
        """JSON-ready figures (fractions rounded to 4 places, None for NaN)."""
        def r(x):
            return None if not math.isfinite(x) else round(float(x), 4)

        return {"removals": self.n_removed, "visible": self.n_visible,
                "hidden": self.n_hidden, "visible_fraction": r(self.fraction),
                "by_structure": {k: {"removals": v.n_removed, "visible": v.n_visible,
                                     "visible_fraction": r(v.fraction)}
                                 for k, v in self.by_structure.items()},
                "live_mismatches": self.live_mismatches}


# ------------------------------------------------------------------ recompute
def _check_session(session) -> None:
    for g in ("samples", "tissue", "camera"):
        if not isinstance(getattr(session, g, None), dict):
            raise ValueError(f"session: no {g!r} stream (expected a Session from "
                             "bonesim.session.reader.read_session)")
    for c in ("kind", "t_s", "ijk", "body", "label"):
        if c not in session.tissue:
            raise ValueError(f"session: the tissue stream has no {c!r} column")
    for c in ("t_s", "pos_mm", "burr"):
        if c not in session.samples:
            raise ValueError(f"session: the samples stream has no {c!r} column")


def _eye0(models, eye_mm):
    if eye_mm is not None:
        eye = np.asarray(eye_mm, np.float64)
        if eye.shape != (3,) or not np.isfinite(eye).all():
            raise ValueError(f"eye_mm must be 3 finite numbers, got {eye_mm!r}")
        return eye
    cam = getattr(getattr(models[0], "case", None), "camera", None)
    if cam is None:
        raise ValueError("eye_mm: the case has no camera; give the eye used before the "
                         "first logged camera pose")
    return np.asarray(cam.eye_mm, np.float64)


def _judge(session, models, eye0):
    """(visible column per tissue row, case-frame centre per removal [mm])."""
    from bonesim.physics.visibility import VisibilityTracker

    tis = session.tissue
    kinds = np.asarray(tis["kind"])
    n = len(kinds)
    rem = kinds == events.REMOVED
    n_rem = int(rem.sum())
    vis = np.full(n, -1, np.int8)
    centre = np.empty((n_rem, 3))
    if n_rem == 0:
        return vis, centre
    s = session.samples
    burr = np.asarray(s["burr"], np.int64)
    if len(burr) and (burr.min() < 0 or burr.max() >= len(models)):
        raise ValueError(f"models: the samples use burr index {int(burr.max())} but "
                         f"{len(models)} model(s) were given")
    tr = VisibilityTracker(models, eye0)
    tr.add_samples({"t_s": np.asarray(s["t_s"], np.float64), "pos_mm": s["pos_mm"],
                    "burr": burr})
    cam = session.camera
    if len(cam.get("t_s", ())):
        tr.add_camera({"t_s": np.asarray(cam["t_s"], np.float64), "eye_mm": cam["eye_mm"]})
    cols = {k: v for k, v in tis.items() if k != "visible"}
    # one judge call per run of removals; the events between runs go to the
    # tracker's replica (resets, burr changes, splits, poses)
    cut = np.concatenate(([0], np.flatnonzero(rem[1:] != rem[:-1]) + 1, [n]))
    grid = tr.initial
    q = 0
    for a, b in zip(cut[:-1], cut[1:]):
        part = {k: v[a:b] for k, v in cols.items()}
        vis[a:b] = tr.judge(part)
        if not rem[a]:
            continue
        ijk = np.asarray(part["ijk"], np.float64)
        c = np.asarray(grid.origin_mm, np.float64) + float(grid.spacing_mm) * ijk
        body = np.asarray(part["body"], np.int64)
        st = tr.replica.state
        for bd in np.unique(body):
            sel = body == bd
            if bd > 0 or not _identity(st.pose[bd]):
                c[sel] = to_case_frame(st.pose_m[bd], c[sel])
        centre[q:q + (b - a)] = c
        q += b - a
    return vis, centre


def _identity(pose) -> bool:
    return bool(np.array_equal(np.asarray(pose, np.float64),
                               [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))


def recompute_visible(session, models=None, eye_mm=None) -> np.ndarray:
    """The ``visible`` column of a session's tissue stream, from the file alone.

    Parameters
    ----------
    session : bonesim.session.reader.Session
        A recorded run (:func:`~bonesim.session.reader.read_session`).
    models : list of Model, optional
        One per burr index (default :meth:`Session.burr_models`, which
        rebuilds them from the recorded case and burrs and checks their
        hashes).
    eye_mm : (3,) float, optional
        Eye before the first logged camera pose [mm], case frame (default:
        the case camera's, as the recorder uses).

    Returns
    -------
    visible : (n_events,) int8
        Per tissue event: 1 visible, 0 hidden for removals, -1 for other
        kinds; what the recorder wrote live.

    Raises
    ------
    ValueError
        The session lacks a stream or column, a removal has no sample of
        its step, the samples name a burr without a model, or there is no
        eye (no case camera and no ``eye_mm``).
    """
    _check_session(session)
    models = session.burr_models() if models is None else list(models)
    if not models:
        raise ValueError("models: need at least one model")
    has_rem = bool(np.any(np.asarray(session.tissue["kind"]) == events.REMOVED))
    eye0 = _eye0(models, eye_mm) if has_rem else np.zeros(3)
    return _judge(session, models, eye0)[0]


# ------------------------------------------------------------------- results
def _names(session, models) -> dict:
    names = {0: "empty"}
    for s in session.header.get("structures", ()) if isinstance(session.header, dict) else ():
        names[int(s["label"])] = str(s["name"])
    if len(names) == 1 and models:
        for lab, st in enumerate(models[0].structures, start=1):
            names[lab] = str(st.name)
    return names


def _windows(t, vis, t0, t1, window_s):
    m = max(1, int(math.ceil((t1 - t0) / window_s - 1e-9)))
    start = t0 + window_s * np.arange(m)
    # window w: start[w] <= t < start[w + 1] (the first and last take what
    # lies before or after them)
    w = np.clip(np.searchsorted(start, t, side="right") - 1, 0, m - 1)
    n_w = np.bincount(w, minlength=m)
    v_w = np.bincount(w, weights=(vis == 1).astype(np.float64), minlength=m).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(n_w > 0, v_w / np.maximum(n_w, 1), np.nan)
        cn, cv = np.cumsum(n_w), np.cumsum(v_w)
        cum = np.where(cn > 0, cv / np.maximum(cn, 1), np.nan)
    return start, n_w, v_w, frac, cum


def visibility(session, window_s: float = WINDOW_S, models=None,
               eye_mm=None) -> VisibilityResult:
    """Voxel visibility of a recorded run, recomputed from the file.

    Parameters
    ----------
    session : bonesim.session.reader.Session
    window_s : float
        Window length of the over-time fraction [s], > 0.
    models, eye_mm
        See :func:`recompute_visible`.

    Returns
    -------
    VisibilityResult
        A run without removals gives zero counts and NaN fractions.

    Raises
    ------
    ValueError
        ``window_s`` not a positive finite number, or see
        :func:`recompute_visible`.
    """
    if not (isinstance(window_s, (int, float)) and math.isfinite(window_s) and window_s > 0):
        raise ValueError(f"window_s must be a positive number of seconds, got {window_s!r}")
    _check_session(session)
    kinds = np.asarray(session.tissue["kind"])
    rem = kinds == events.REMOVED
    if models is None:
        models = session.burr_models() if rem.any() else []
    models = list(models)
    if rem.any() and not models:
        raise ValueError("models: need at least one model")
    eye0 = _eye0(models, eye_mm) if rem.any() else np.zeros(3)
    col, centre = _judge(session, models, eye0) if rem.any() else \
        (np.full(len(kinds), -1, np.int8), np.empty((0, 3)))
    tis = session.tissue
    t = np.asarray(tis["t_s"], np.float64)[rem]
    vis = col[rem]
    rec = np.asarray(tis["visible"], np.int8)[rem] if "visible" in tis \
        else np.full(len(vis), -1, np.int8)
    label = np.asarray(tis["label"], np.uint8)[rem]
    st = np.asarray(session.samples["t_s"], np.float64)
    if len(st):
        epoch = np.asarray(session.samples["epoch"])[
            np.clip(np.searchsorted(st, t), 0, len(st) - 1)] if "epoch" in session.samples \
            else np.zeros(len(t), np.int64)
        t0, t1 = float(st[0]), float(st[-1])
    else:
        epoch = np.zeros(len(t), np.int64)
        t0 = float(t[0]) if len(t) else 0.0
        t1 = float(t[-1]) if len(t) else 0.0
    names = _names(session, models)
    n = len(vis)
    nv = int(np.sum(vis == 1))
    by = {}
    for lab in np.unique(label):
        sel = label == lab
        k, kv = int(sel.sum()), int(np.sum(vis[sel] == 1))
        by[names.get(int(lab), f"label {int(lab)}")] = StructureVisibility(
            int(lab), k, kv, kv / k)
    start, n_w, v_w, frac, cum = _windows(t, vis, t0, t1, float(window_s))
    known = rec >= 0
    return VisibilityResult(
        t_s=t, visible=vis, recorded=rec, label=label, centre_mm=centre,
        epoch=np.asarray(epoch), n_removed=n, n_visible=nv,
        fraction=nv / n if n else math.nan, by_structure=by, window_s=float(window_s),
        window_start_s=start, window_removed=n_w, window_visible=v_w,
        window_fraction=frac, cumulative_fraction=cum,
        live_mismatches=int(np.sum(rec[known] != vis[known])), names=names)


def visible_fraction(session, models=None, eye_mm=None) -> float:
    """Fraction of a run's removals that were visible when removed
    (recomputed, see :func:`visibility`); NaN for a run without removals."""
    return visibility(session, models=models, eye_mm=eye_mm).fraction


# ---------------------------------------------------------------------- view
def _chosen(models, structures):
    """Names of the structures to draw (default: every non-bone one)."""
    sts = list(models[0].structures)
    names = [st.name for st in sts]
    if structures is None:
        return [st.name for st in sts if st.kind != "bone"]
    if isinstance(structures, str):
        structures = [structures]
    chosen = [str(s) for s in structures]
    unknown = [s for s in chosen if s not in names]
    if unknown:
        raise ValueError(f"structures: unknown {unknown}; the case has {names}")
    return chosen


def _legend(result, session):
    """HUD lines: title, fractions, colour key."""
    h = session.header if isinstance(session.header, dict) else {}
    who = h.get("participant") or ""
    case = (h.get("case") or {}).get("name", "")
    title = "Voxel visibility at removal" + (f" - {case}" if case else "") + \
        (f" - {who}" if who else "")
    if result.n_removed:
        lines = [f"{result.fraction * 100:.1f} % visible  "
                 f"({result.n_visible:,} of {result.n_removed:,} removals; "
                 f"{result.n_hidden:,} hidden)"]
        for name, v in sorted(result.by_structure.items(), key=lambda kv: -kv[1].n_removed):
            lines.append(f"  {clinical_name(name)}: {v.fraction * 100:.1f} % of "
                         f"{v.n_removed:,}")
    else:
        lines = ["no voxel was removed"]
    return title, lines


def _scene(session, structures, size, result, view, models, offscreen):
    sz = tuple(int(v) for v in np.asarray(size).ravel()) if np.size(size) == 2 else ()
    if len(sz) != 2 or min(sz) < 16 or max(sz) > 8192:
        raise ValueError(f"size must be (width, height) in pixels, 16..8192, got {size!r}")
    models = session.burr_models() if models is None else list(models)
    if not models:
        raise ValueError("models: need at least one model")
    chosen = _chosen(models, structures)
    res = visibility(session, models=models) if result is None else result
    title, lines = _legend(res, session)
    return visibility_scene(models[0], res.centre_mm, res.visible, chosen, title, lines,
                            size=sz, offscreen=offscreen, view=view)


def render_visibility(session, path, structures=None, size=(1024, 768), *, result=None,
                      view=None, models=None):
    """Draw a run's removed voxels coloured by visibility to a PNG, offscreen.

    The removed voxels are small cubes at their case-frame centres (each
    moved with its body's pose at its removal), green when the voxel was
    visible at its removal and red when it was hidden; the bone is not
    drawn, the chosen structures are, seen from the case camera
    (:func:`bonesim.render.visibility_view.visibility_scene`). Text gives
    the visible fraction overall and per structure and the colour key.

    Parameters
    ----------
    session : bonesim.session.reader.Session
    path : path
        PNG to write (folders are made).
    structures : sequence of str, optional
        Structure names to show (default: every structure of the case that
        is not bone).
    size : (2,) int
        Image width, height [pixels].
    result : VisibilityResult, optional
        Already computed (default: :func:`visibility` of ``session``).
    view : (eye_mm, focal_mm, up), optional
        Camera, case frame [mm] (default: the case camera).
    models : list of Model, optional
        See :func:`recompute_visible`.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        Bad ``size`` or unknown structure names.
    bonesim.render.gl.RenderUnavailable
        No offscreen OpenGL.
    """
    from pathlib import Path

    scene = _scene(session, structures, size, result, view, models, offscreen=True)
    try:
        scene.screenshot(Path(path))
    finally:
        scene.close()
    return Path(path)


def show_visibility(session, structures=None, size=(1024, 768), *, result=None, view=None,
                    models=None, frames=None, screenshot=None) -> dict:
    """Open the visibility view of :func:`render_visibility` in a window to
    turn it about with the mouse (left drag orbits, the wheel zooms, ``c``
    saves a picture, ``v`` goes back to the case camera, ``q`` closes).

    Parameters are :func:`render_visibility`'s, and ``frames`` (stop after
    this many) and ``screenshot`` (save the last frame). Returns the window's
    summary.

    Raises
    ------
    bonesim.render.gl.RenderUnavailable
        No display (use :func:`render_visibility` for a picture).
    """
    scene = _scene(session, structures, size, result, view, models, offscreen=False)
    try:
        return show_visibility_window(scene, frames=frames, screenshot=screenshot)
    finally:
        scene.close()
