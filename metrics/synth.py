"""Synthetic cohorts: scripted runs of a case by expert-like and novice-like
behaviour models, recorded through the engine. **Test data, not people.**

A study's metrics need runs of two groups. Until recorded runs of real
residents and surgeons exist, :func:`synth_cohort` makes them: each
participant gets a behaviour drawn from their group's model with a
per-participant skill and noise, a scripted trajectory is planned from it on
the case, and the trajectory is drilled and recorded at the haptic rate by
:func:`bonesim.runtime.simulate.run_trajectory`, exactly as ``bonesim
simulate --record`` does. The metrics read only the session files and the
participants table (``id, group, instructor_score``), never the behaviour.

Behaviour models
----------------
Expert-like (:class:`ExpertModel`)
    The layered saucerizing mastoidectomy of :mod:`bonesim.io.toolpath`
    (broad raster passes over the cortex, one layer deeper per pass, along
    the surgeon's line of sight, so the burr stays in view) with a large
    cutting burr, changed for a smaller diamond burr on the passes that come
    near a structure, a margin kept from every structure, a slower feed near
    near them, and per-participant region, layer depth, feed and margin. For
    the last ``near_share`` of the run the expert thins the bone over the
    facial nerve or the chorda tympani (a place where it lies a few mm under
    the bone): drill resting, burr changed for the diamond, then down along
    the line of sight at a very slow feed (light touch: forces well under the
    clamp) with small side strokes, to a margin from the structure, and
    polishing there.
Novice-like (:class:`NoviceModel`)
    Deep narrow holes with a smaller burr: a plunge along the line of sight
    at a steady fast feed down to a small margin from the structures beneath
    (some participants overshoot: an injury), then a sideways sweep at depth
    that undercuts the rim (removals hidden from the eye), back, and out;
    hole after hole around the focal axis, a share of them (``aim_share``)
    aimed at the same nerves the expert thins over.

Sessions and learning (:class:`Learning`)
    A participant may drill several sessions. Session ``k`` (from 1) draws
    with the skill ``skill + per_session * (k - 1)`` of their group and its
    own seed: a novice's margins grow, plunges slow, undercuts shorten and
    overshoots grow rarer session by session; experts change little. The
    instructor score of a session follows the skill.

The parameters of every model are data: ``metrics/synth.toml``
(:func:`load_behaviours`; what ``bonesim cohort synth`` uses; the Python
function without ``behaviours`` keeps the classes' defaults, the models
before the thinning phase and the aimed holes); ``synthesis.json`` beside
the cohort records the seed, the counts and every parameter used.

Every draw comes from one seeded generator: the same seed gives the same
cohort. The participants' instructor scores are drawn around the reference
study's group means (surgeons 4.06, novices 2.31 on a 5-point scale,
``SPEC.md``) and rise with the participant's skill, which also shapes their
behaviour, so the scores correlate with the runs within a group too.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = ["ExpertModel", "NoviceModel", "Learning", "Participant", "draw_participants",
           "expert_trajectory", "novice_trajectory", "synth_cohort", "PARTICIPANTS_CSV",
           "SCORE_RANGE", "BEHAVIOURS_FILE", "load_behaviours", "session_participant"]

#: Name of the participants table written beside the sessions.
PARTICIPANTS_CSV = "participants.csv"
#: Instructor scores lie in this range (a 5-point global rating).
SCORE_RANGE = (1.0, 5.0)
#: Rate of the planned trajectory points [Hz] (``simulate`` resamples them).
_SAMPLE_HZ = 100.0
#: Step of the search for the first bone along a ray [mm].
_RAY_STEP_MM = 0.25
#: Longest search for bone along the line of sight [mm].
_RAY_MAX_MM = 60.0
#: Hole centres tried in a row without bone under them before giving up.
_MAX_MISSES = 200
#: The behaviour parameters of :func:`synth_cohort` (:func:`load_behaviours`).
BEHAVIOURS_FILE = Path(__file__).with_name("synth.toml")


@dataclass(frozen=True)
class ExpertModel:
    """The expert-like behaviour (see the module docstring); means and
    per-participant standard deviations.

    Attributes
    ----------
    burr : str
        Burr used throughout.
    region_radius_mm, region_sd_mm : float
        Radius of the saucerized region [mm].
    layer_mm, layer_sd_mm : float
        Depth per pass [mm].
    speed_mm_s, speed_sd_mm_s : float
        Feed along the passes [mm/s].
    margin_mm, margin_sd_mm : float
        Margin kept from every structure that is not bone [mm].
    centre_sd_mm : float
        Offset of the region's centre from the focal axis, per axis [mm].
    slow_within_mm : float
        The feed slows down where the burr's surface comes within this much
        of the margin from a structure [mm] ...
    slow_share : float
        ... linearly, to this share of the feed at the margin (a slower feed
        cuts less bone per second: less force).
    fine_burr : str
        The smaller burr of the passes near structures (burr 1 of the run;
        ``burr`` is burr 0) ...
    fine_within_mm : float
        ... used for every drilling pass whose burr surface lies, at the
        median of the pass, within this much of the margin from a structure
        (the deep layers); it goes in, at its own default speed, while the
        drill rests before the pass.
    score, score_sd : float
        Instructor score mean and spread.
    near_share : float
        Share of the run (with ``duration_s``) spent thinning over a nerve
        (``_near_phase``); 0: none.
    near_targets : tuple of str
        Structures thinned over ...
    near_depth_mm : (float, float)
        ... at places this deep under the first bone seen from the eye [mm].
    near_fast_mm_s, near_within_mm : float
        Feed [mm/s] of the cutting burr down to this gap from a structure [mm].
    near_feed_mm_s : float
        The diamond's light-touch feed below it [mm/s] ...
    near_stroke_mm, near_stroke_s : float
        ... with side strokes of this amplitude [mm] and period [s] ...
    near_margin_mm : float
        ... down to this gap from a structure [mm].
    near_tilt_deg : float
        Burr axis tilt from the line of sight while thinning [deg].
    travel_mm_s : float
        Speed of moves with the drill off [mm/s].
    """

    burr: str = "cutting-5mm"
    region_radius_mm: float = 9.0
    region_sd_mm: float = 0.7
    layer_mm: float = 0.6
    layer_sd_mm: float = 0.08
    speed_mm_s: float = 8.0
    speed_sd_mm_s: float = 2.0
    margin_mm: float = 1.2
    margin_sd_mm: float = 0.15
    centre_sd_mm: float = 0.8
    slow_within_mm: float = 4.0
    slow_share: float = 0.15
    fine_burr: str = "diamond-4mm"
    fine_within_mm: float = 3.0
    score: float = 4.06
    score_sd: float = 0.35
    near_share: float = 0.0
    near_targets: tuple = ("facial_nerve", "chorda_tympani")
    near_depth_mm: tuple = (1.5, 4.0)
    near_feed_mm_s: float = 0.12
    near_stroke_mm: float = 0.5
    near_stroke_s: float = 3.0
    near_margin_mm: float = 1.0
    near_tilt_deg: float = 60.0
    near_fast_mm_s: float = 2.0
    near_within_mm: float = 4.5
    travel_mm_s: float = 40.0


@dataclass(frozen=True)
class NoviceModel:
    """The novice-like behaviour (see the module docstring).

    Attributes
    ----------
    burr : str
        Burr used throughout (smaller than the expert's).
    spread_mm : float
        Hole centres lie within this distance of the focal axis [mm].
    plunge_mm_s, plunge_sd_mm_s : float
        Feed of the plunge along the line of sight [mm/s].
    plunge_learning : float
        Share of the plunge feed that skill takes off: the feed is
        ``plunge_mm_s * (1 - plunge_learning * tanh(skill))`` (a lighter
        touch as a novice learns; faster than ``plunge_mm_s`` below skill 0).
    min_plunge_mm_s : float
        Slowest plunge [mm/s].
    margin_mm, margin_sd_mm : float
        Margin from the structures at which a plunge or sweep stops [mm].
    overshoot_p, overshoot_mm : float
        Share of participants who overshoot, and by how much past the
        structures' surface they plunge [mm].
    undercut_mm, undercut_sd_mm : float
        Length of the sideways sweep at depth [mm].
    undercut_rise_mm : float
        The sweep runs this far above the hole's floor [mm].
    sweep_mm_s : float
        Feed of the sweep [mm/s].
    travel_mm_s : float
        Speed out of and between holes [mm/s].
    max_depth_mm : float
        Deepest plunge below the first bone [mm].
    score, score_sd : float
        Instructor score mean and spread.
    aim_share : float
        Share of the holes centred over a place of ``near_targets`` (the
        expert's, :func:`_near_targets`) instead of around the focal axis.
    near_targets : tuple of str
    near_depth_mm : (float, float)
        As the expert's.
    aim_sd_mm : float
        Scatter of an aimed hole's centre [mm].
    """

    burr: str = "cutting-3mm"
    spread_mm: float = 5.0
    plunge_mm_s: float = 6.0
    plunge_sd_mm_s: float = 1.0
    plunge_learning: float = 0.12
    min_plunge_mm_s: float = 2.0
    margin_mm: float = 0.3
    margin_sd_mm: float = 0.15
    overshoot_p: float = 0.35
    overshoot_mm: float = 0.4
    undercut_mm: float = 3.0
    undercut_sd_mm: float = 0.8
    undercut_rise_mm: float = 1.0
    sweep_mm_s: float = 8.0
    travel_mm_s: float = 40.0
    max_depth_mm: float = 14.0
    score: float = 2.31
    score_sd: float = 0.45
    aim_share: float = 0.0
    near_targets: tuple = ("facial_nerve", "chorda_tympani")
    near_depth_mm: tuple = (1.5, 4.0)
    aim_sd_mm: float = 1.0


@dataclass(frozen=True)
class Learning:
    """How skill changes from session to session (module docstring).

    Attributes
    ----------
    expert_per_session, novice_per_session : float
        Skill gained per session [standard deviations of skill].
    score_per_skill : float
        Instructor score gained per unit of skill gained [points].
    """

    expert_per_session: float = 0.1
    novice_per_session: float = 0.9
    score_per_skill: float = 0.35


def load_behaviours(path=None) -> tuple:
    """``(ExpertModel, NoviceModel, Learning)`` from a TOML file (default
    :data:`BEHAVIOURS_FILE`) with tables ``[expert]``, ``[novice]`` and
    ``[learning]``; fields it omits keep the classes' defaults.

    Raises
    ------
    BonesimError
        Naming the file and the key: unreadable TOML, an unknown field.
    """
    import tomllib
    from dataclasses import fields

    from bonesim.errors import BonesimError

    path = Path(BEHAVIOURS_FILE if path is None else path)
    try:
        d = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BonesimError(f"{path}: cannot read the behaviours "
                           f"({' '.join(str(exc).split())})") from None
    out = []
    for key, cls in (("expert", ExpertModel), ("novice", NoviceModel), ("learning", Learning)):
        got = d.get(key, {})
        names = {f.name for f in fields(cls)}
        bad = sorted(set(got) - names)
        if bad:
            raise BonesimError(f"{path}: [{key}] {bad[0]!r} is not a field of "
                               f"{cls.__name__} ({', '.join(sorted(names))})")
        out.append(cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in got.items()}))
    return tuple(out)


def session_participant(p: "Participant", session: int, learning: Learning) -> "Participant":
    """Participant ``p`` at session ``session`` (1, 2, ...): skill raised by
    their group's learning rate, instructor score with it, a seed of its own."""
    gain = (learning.expert_per_session if p.group == "expert"
            else learning.novice_per_session) * (session - 1)
    score = float(np.clip(p.instructor_score + learning.score_per_skill * gain, *SCORE_RANGE))
    return replace(p, skill=p.skill + gain, instructor_score=round(score, 2),
                   seed=int((p.seed + 7919 * (session - 1)) % (2**31 - 1)))


@dataclass(frozen=True)
class Participant:
    """One synthetic participant.

    Attributes
    ----------
    id : str
    group : {"expert", "novice"}
    skill : float
        Standard normal; shifts the behaviour toward the better end and
        raises the instructor score.
    instructor_score : float
        On :data:`SCORE_RANGE`.
    seed : int
        Seed of this participant's own draws (trajectory noise).
    """

    id: str
    group: str
    skill: float
    instructor_score: float
    seed: int


def draw_participants(experts: int, novices: int, seed: int = 0,
                      expert: ExpertModel = ExpertModel(),
                      novice: NoviceModel = NoviceModel()) -> list[Participant]:
    """Participants ``E01..`` and ``N01..`` with skills and instructor scores.

    Raises
    ------
    ValueError
        If a count is negative or both are 0.
    """
    if experts < 0 or novices < 0 or experts + novices == 0:
        raise ValueError(f"need experts >= 0, novices >= 0 and at least one run, got "
                         f"{experts} and {novices}")
    rng = np.random.default_rng(seed)
    out = []
    for group, n, m in (("expert", experts, expert), ("novice", novices, novice)):
        for q in range(n):
            skill = float(rng.standard_normal())
            score = float(np.clip(m.score + m.score_sd * (0.7 * skill
                                                          + 0.7 * rng.standard_normal()),
                                  *SCORE_RANGE))
            out.append(Participant(f"{group[0].upper()}{q + 1:02d}", group, skill,
                                   round(score, 2), int(rng.integers(2**31 - 1))))
    return out


# ------------------------------------------------------------------ geometry
def _view(case):
    eye = np.asarray(case.camera.eye_mm, float)
    focal = np.asarray(case.camera.focal_mm, float)
    v = focal - eye
    v /= np.linalg.norm(v)
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(v, a)
    u /= np.linalg.norm(u)
    return eye, focal, v, u, np.cross(v, u)


def _first_bone(grid, start, v):
    """Distance [mm] along ``v`` from ``start`` to the first voxel with
    density, or None."""
    t = np.arange(0.0, _RAY_MAX_MM, _RAY_STEP_MM)
    pts = start + t[:, None] * v
    ijk = np.floor((pts - grid.origin_mm) / grid.spacing_mm + 0.5).astype(np.int64)
    for q in range(len(t)):
        if grid.density_at(*ijk[q]) > 0.0:
            return float(t[q])
    return None


class _Path:
    """Waypoints joined at given speeds, sampled at :data:`_SAMPLE_HZ`."""

    def __init__(self, start):
        self.t = [0.0]
        self.p = [np.asarray(start, float)]
        self.drill = [False]

    def go(self, p, speed_mm_s, drill):
        p = np.asarray(p, float)
        d = float(np.linalg.norm(p - self.p[-1]))
        n = max(int(math.ceil(d / speed_mm_s * _SAMPLE_HZ)), 1)
        for k in range(1, n + 1):
            self.t.append(self.t[-1] + 1.0 / _SAMPLE_HZ)
            self.p.append(self.p[-1] + (p - self.p[-1]) / (n - k + 1))
            self.drill.append(bool(drill))

    @property
    def duration(self):
        return self.t[-1]

    def trajectory(self, v, speed_rpm, duration_s=None):
        """The path up to ``duration_s`` [s], drill axis ``v`` (the line of sight)."""
        from bonesim.io.trajectory import Trajectory

        t = np.asarray(self.t)
        n = len(t) if duration_s is None else int(np.count_nonzero(t <= duration_s))
        return Trajectory(t[:n], np.asarray(self.p)[:n], np.tile(v, (n, 1)),
                          np.asarray(self.drill)[:n], np.full(n, float(speed_rpm)))


# --------------------------------------------------------------- behaviours
def expert_trajectory(case, clearance, participant: Participant,
                      model: ExpertModel = ExpertModel(), duration_s: float | None = None,
                      grid=None):
    """The expert-like run of ``participant`` on ``case`` (module docstring).

    Parameters
    ----------
    case : bonesim.io.case.Case
    clearance : bonesim.physics.clearance.Clearance
        Distances to the case's structures (the model's): the feed slows
        near them.
    participant : Participant
    model : ExpertModel
    duration_s : float, optional
        Cut the run at this time [s].
    grid : bonesim.engine.grid.Grid, optional
        The case's bone: needed for the thinning phase (``near_share``), which
        runs only with ``duration_s``.

    Returns
    -------
    bonesim.io.trajectory.Trajectory
        Burr centres [mm], case frame; cut at ``duration_s`` [s] if given.
    """
    from bonesim.io.toolpath import load_demo_plan, plan_mastoidectomy

    rng = np.random.default_rng(participant.seed)
    s = participant.skill
    plan = replace(load_demo_plan(),
                   region_radius_mm=model.region_radius_mm + model.region_sd_mm
                   * rng.standard_normal(),
                   layer_mm=max(0.3, model.layer_mm + model.layer_sd_mm * rng.standard_normal()),
                   speed_mm_s=max(4.0, model.speed_mm_s - 0.5 * model.speed_sd_mm_s * s
                                  + model.speed_sd_mm_s * rng.standard_normal()),
                   margin_mm=max(0.5, model.margin_mm + 0.5 * model.margin_sd_mm * s
                                 + model.margin_sd_mm * rng.standard_normal()))
    off = model.centre_sd_mm * rng.standard_normal(3)
    cam = case.camera
    moved = replace(case, declared_camera=replace(
        cam, eye_mm=tuple(np.add(cam.eye_mm, off)), focal_mm=tuple(np.add(cam.focal_mm, off))))
    # the planned mastoidectomy as a surgeon drills it: the cutting burr for
    # the bulk, the diamond burr for the finishing strokes near the structures
    # (only the part a run of duration_s reaches: retimed below, the run is
    # never faster than the plan, so the plan's first duration_s suffice)
    planned = plan_mastoidectomy(moved, model.burr, model.fine_burr, plan,
                                 until_s=duration_s).trajectory
    traj = _slow_near_structures(planned, case, clearance, plan.margin_mm, model,
                                 stages=planned.burr)
    if model.near_share > 0 and duration_s is not None and grid is not None:
        t1 = (1.0 - model.near_share) * duration_s
        first = traj.at_times(traj.t_s[traj.t_s <= t1])
        return _near_phase(first, case, grid, clearance, rng, model, duration_s)
    return traj if duration_s is None else traj.at_times(traj.t_s[traj.t_s <= duration_s])


def _danger(case) -> list:
    return [k for k, st in enumerate(case.structures, start=1) if st.kind != "bone"]


def _near_targets(case, grid, names, depth_mm) -> np.ndarray:
    """Centres [mm] of voxels of the structures ``names`` that lie between
    ``depth_mm`` (min, max) under the first bone along the line of sight,
    ``(m, 3)``; cached per case."""
    key = (case.name, tuple(names), tuple(depth_mm))
    if key in _TARGETS:
        return _TARGETS[key]
    _, _, v, _, _ = _view(case)
    _, lab = grid.to_dense()
    want = [k for k, st in enumerate(case.structures, start=1) if st.name in names]
    out = []
    for k in want:
        ijk = np.argwhere(lab == k)
        for q in ijk[:: max(1, len(ijk) // 400)]:
            p = grid.origin_mm + grid.spacing_mm * q
            t = _first_bone(grid, p - 40.0 * v, v)
            if t is not None and depth_mm[0] <= 40.0 - t <= depth_mm[1]:
                out.append(p)
    _TARGETS[key] = np.asarray(out, float).reshape(-1, 3)
    return _TARGETS[key]


_TARGETS: dict = {}


def _near_phase(first, case, grid, clearance, rng, model, duration_s):
    """``first`` followed by the expert's thinning over a nerve (module
    docstring) until ``duration_s`` [s]: out and over to the target, down the
    line from the eye with the cutting burr (burr 0) at ``near_fast_mm_s``
    until its surface is ``near_within_mm`` from a structure, the drill
    resting while the diamond (burr 1) goes in, then on at the light-touch
    feed with side strokes, tilted, to ``near_margin_mm``, and polishing
    there."""
    from bonesim.io.burrs import load_burr
    from bonesim.io.trajectory import Trajectory

    big, fine = load_burr(model.burr), load_burr(model.fine_burr)
    eye, focal, v, u, w = _view(case)
    targets = _near_targets(case, grid, model.near_targets, model.near_depth_mm)
    if not len(targets):
        return first
    tgt = targets[rng.integers(len(targets))]
    # down the line from the eye to the target: every removal stays in view
    v = tgt - eye
    v /= np.linalg.norm(v)
    u = np.cross(v, w)
    u /= np.linalg.norm(u)
    w = np.cross(u, v)
    groups = clearance.group_mask([_danger(case)])
    a0 = tgt - 40.0 * v
    hit = _first_bone(grid, a0, v)
    if hit is None:
        return first
    top = a0 + (hit - 1.0) * v
    start = first.pos_mm[-1] if len(first.t_s) else top - 15.0 * v

    def gap(p, r):
        return float(clearance.distances(np.asarray(p)[None], groups)[0, 0]) - r

    dt = 1.0 / _SAMPLE_HZ
    t0 = first.t_s[-1] if len(first.t_s) else 0.0
    pos, drill, burr, tilted = [], [], [], []

    def seg(p_from, p_to, speed, on, b, tilt=False):
        n = max(int(math.ceil(np.linalg.norm(p_to - p_from) / speed * _SAMPLE_HZ)), 1)
        for k in range(1, n + 1):
            pos.append(p_from + (p_to - p_from) * k / n)
            drill.append(on)
            burr.append(b)
            tilted.append(tilt)

    b0 = int(first.burr[-1]) if first.burr is not None and len(first.t_s) else 0
    seg(start, start - 15.0 * v, model.travel_mm_s, False, b0)
    seg(start - 15.0 * v, top - 14.0 * v, model.travel_mm_s, False, b0)
    seg(top - 14.0 * v, top, model.travel_mm_s / 4, False, 0)
    depth = 0.0
    step = model.near_fast_mm_s * dt
    while gap(top + (depth + step) * v, big.radius_mm) > model.near_within_mm and \
            depth < _RAY_MAX_MM and t0 + len(pos) * dt < duration_s:
        depth += step
        pos.append(top + depth * v)
        drill.append(True)
        burr.append(0)
        tilted.append(False)
    here = top + depth * v
    seg(here, here - 0.5 * v, 2.0, False, 1)            # lift off; the diamond goes in
    seg(here - 0.5 * v, here, 1.0, False, 1)
    k = 0
    r = float(fine.radius_mm)
    while t0 + (len(pos) + 1) * dt <= duration_s:
        nxt = depth + model.near_feed_mm_s * dt
        if gap(top + nxt * v, r) > model.near_margin_mm:
            depth = nxt
        k += 1
        side = model.near_stroke_mm * math.sin(2 * math.pi * k * dt / model.near_stroke_s)
        pos.append(top + depth * v + side * u)
        drill.append(True)
        burr.append(1)
        tilted.append(True)
    n = len(pos)
    t = t0 + dt * np.arange(1, n + 1)
    keep = t <= duration_s
    tilt = math.radians(model.near_tilt_deg)
    ax = np.where(np.asarray(tilted)[:, None], math.cos(tilt) * v + math.sin(tilt) * w, v)
    burr = np.asarray(burr, np.uint8)
    rpm = np.where(burr == 1, fine.default_speed_rpm, big.default_speed_rpm).astype(float)
    f = first
    burr0 = f.burr if f.burr is not None else np.zeros(len(f.t_s), np.uint8)
    return Trajectory(np.concatenate([f.t_s, t[keep]]),
                      np.concatenate([f.pos_mm, np.asarray(pos).reshape(-1, 3)[keep]]),
                      np.concatenate([f.axis, ax[keep]]),
                      np.concatenate([f.drill, np.asarray(drill, bool)[keep]]),
                      np.concatenate([f.speed_rpm, rpm[keep]]), None, None, None,
                      np.concatenate([burr0, burr[keep]]))


def _slow_near_structures(traj, case, clearance, margin_mm, model, stages=None):
    """``traj`` retimed and with its burr stages: each drilling step takes
    ``1 / f`` as long, ``f`` falling linearly from 1 (burr surface
    ``margin + slow_within_mm`` from a structure) to ``slow_share`` (at the
    margin); a drilling pass that comes within ``fine_within_mm`` of the
    margin uses the fine burr (burr 1), changed while the drill rests before
    it; or, given ``stages`` (a burr per sample: a plan's own), those burrs."""
    from bonesim.io.burrs import load_burr
    from bonesim.io.trajectory import Trajectory

    big, fine = load_burr(model.burr), load_burr(model.fine_burr)
    r = float(big.radius_mm)
    danger = [k for k, st in enumerate(case.structures, start=1) if st.kind != "bone"]
    gap = clearance.distances(traj.pos_mm, clearance.group_mask([danger]))[:, 0] - r
    f = np.clip((gap - margin_mm) / model.slow_within_mm, 0.0, 1.0)
    f = model.slow_share + (1.0 - model.slow_share) * f
    f = np.where(traj.drill, f, 1.0)
    dt = np.diff(traj.t_s) / f[1:]
    t = np.concatenate(([traj.t_s[0]], traj.t_s[0] + np.cumsum(dt)))
    burr = (_burr_stages(traj.drill, gap - margin_mm, model.fine_within_mm)
            if stages is None else np.asarray(stages, np.uint8))
    speed = np.where(burr == 1, fine.default_speed_rpm, big.default_speed_rpm)
    return Trajectory(t, traj.pos_mm, traj.axis, traj.drill, speed, traj.direction,
                      traj.suction, traj.irrigation, burr)


def _burr_stages(drill, gap_mm, within_mm: float) -> np.ndarray:
    """Burr per sample: 1 for each drilling pass (a run of ``drill``) whose
    median ``gap_mm`` [mm] is at most ``within_mm``, else 0; the samples
    before a pass (drill resting) take the pass's burr, so every change
    happens with the drill off."""
    drill = np.asarray(drill, bool)
    gap_mm = np.asarray(gap_mm, np.float64)
    n = len(drill)
    burr = np.zeros(n, np.uint8)
    starts = np.flatnonzero(drill & ~np.r_[False, drill[:-1]])
    ends = np.flatnonzero(drill & ~np.r_[drill[1:], False]) + 1
    prev_end = 0
    for a, b in zip(starts, ends):
        burr[prev_end:b] = 1 if np.median(gap_mm[a:b]) <= within_mm else 0
        prev_end = b
    if prev_end < n:
        burr[prev_end:] = burr[prev_end - 1] if prev_end else 0
    return burr


def novice_trajectory(case, grid, clearance, participant: Participant,
                      model: NoviceModel = NoviceModel(), duration_s: float | None = None):
    """The novice-like run of ``participant`` on ``case`` (module docstring).

    Parameters
    ----------
    case : bonesim.io.case.Case
    grid : bonesim.engine.grid.Grid
        The case's bone (where the holes start).
    clearance : bonesim.physics.clearance.Clearance
        Distances to the case's structures (the model's).
    participant : Participant
    model : NoviceModel
    duration_s : float, optional
        Plan holes until the run lasts this long [s] (default: 8 holes).

    Returns
    -------
    bonesim.io.trajectory.Trajectory
    """
    from bonesim.errors import BonesimError
    from bonesim.io.burrs import load_burr

    burr = load_burr(model.burr)
    r = float(burr.radius_mm)
    rng = np.random.default_rng(participant.seed)
    s = participant.skill
    eye, focal, v, u, w = _view(case)
    danger = [k for k, st in enumerate(case.structures, start=1) if st.kind != "bone"]
    groups = clearance.group_mask([danger])

    def gap(p):                      # burr surface to the nearest danger structure [mm]
        return float(clearance.distances(np.asarray(p, float)[None], groups)[0, 0]) - r

    overshoot = rng.random() < model.overshoot_p * (1.0 - 0.5 * np.tanh(s))
    margin = -model.overshoot_mm if overshoot else max(
        0.05, model.margin_mm + model.margin_sd_mm * (0.5 * s + rng.standard_normal()))
    # skill slows the plunge and shortens the undercut
    plunge = max(model.min_plunge_mm_s,
                 model.plunge_mm_s * (1.0 - model.plunge_learning * np.tanh(s))
                 + model.plunge_sd_mm_s * rng.standard_normal())
    under = model.undercut_mm * max(0.2, 1.0 - 0.3 * np.tanh(s))
    targets = _near_targets(case, grid, model.near_targets, model.near_depth_mm) \
        if model.aim_share > 0 else np.zeros((0, 3))
    step = 0.1                                         # plan resolution [mm]
    above = 2.0 * r                                    # start this far above the bone [mm]
    path = None
    holes = misses = 0
    while True:
        if len(targets) and rng.random() < model.aim_share:
            c = targets[rng.integers(len(targets))] + model.aim_sd_mm * (
                rng.standard_normal() * u + rng.standard_normal() * w)
            axis0 = c - np.dot(c - focal, v) * v - 0.5 * _RAY_MAX_MM * v
        else:
            a, b = rng.uniform(-1.0, 1.0, 2) * model.spread_mm
            axis0 = focal + a * u + b * w - 0.5 * _RAY_MAX_MM * v
        t0 = _first_bone(grid, axis0, v)
        if t0 is None:
            misses += 1
            if misses > _MAX_MISSES:
                raise BonesimError(f"no bone under the line of sight within "
                                   f"{model.spread_mm} mm of the focal axis of case "
                                   f"{case.name!r}")
            continue
        top = axis0 + (t0 - above) * v
        if path is None:
            path = _Path(top)
        else:
            path.go(top, model.travel_mm_s, False)
        # plunge along the line of sight until the margin (or the depth cap)
        d = 0.0
        while d < model.max_depth_mm + above and gap(top + (d + step) * v) > margin:
            d += step
        bottom = top + d * v
        path.go(bottom, plunge, True)
        # undercut: sideways at depth, under the rim, while clear
        ang = rng.uniform(0.0, 2.0 * math.pi)
        side = math.cos(ang) * u + math.sin(ang) * w
        length = max(0.5, under + model.undercut_sd_mm * rng.standard_normal())
        base = bottom - model.undercut_rise_mm * v
        x = 0.0
        while x < length and gap(base + (x + step) * side) > margin:
            x += step
        path.go(base, model.sweep_mm_s, True)
        path.go(base + x * side, model.sweep_mm_s, True)
        path.go(base, model.sweep_mm_s, True)
        path.go(top, model.travel_mm_s, False)
        holes += 1
        if (duration_s is not None and path.duration >= duration_s) or \
                (duration_s is None and holes >= 8):
            break
    return path.trajectory(v, burr.default_speed_rpm, duration_s)


# ------------------------------------------------------------------ cohorts
def synth_cohort(out_dir, experts: int = 6, novices: int = 6, *, seed: int = 0,
                 case: str = "phantom", duration_s: float = 180.0,
                 expert: ExpertModel | None = None, novice: NoviceModel | None = None,
                 sessions: int = 1, learning: Learning | None = None,
                 behaviours=None, progress=None) -> list[Path]:
    """Record a synthetic cohort into ``out_dir`` (module docstring).

    Writes a session file per participant and session (``<id>.h5`` with one
    session, ``<id>_s<k>.h5`` with more; the header names the participant,
    not the group), ``participants.csv`` (``id, group, instructor_score,
    session, file``: a row per session), ``synthesis.json`` (seed, counts,
    every parameter) and a ``README.txt`` saying that the data are synthetic.

    Parameters
    ----------
    out_dir : path
        A folder that holds no session files yet (created if missing).
    experts, novices : int
        Participants per group.
    seed : int
        Seed of every draw.
    case : str
        Case name or ``case.toml`` path.
    duration_s : float
        Length of each run [s] (simulated time, at the haptic rate).
    expert, novice, learning : optional
        The behaviours; default those of ``behaviours``.
    sessions : int
        Sessions per participant (>= 1).
    behaviours : path, optional
        A behaviours file (:func:`load_behaviours`; ``bonesim cohort synth``
        passes :data:`BEHAVIOURS_FILE`, the behaviours issue 25 asks for).
        Default: the classes' defaults (the saucerizing expert without the
        thinning phase, novices around the focal axis).
    progress : callable, optional
        Called with ``(done, total)`` after each run.

    Returns
    -------
    list of Path
        The session files, by participant, then session.
    """
    import json
    from dataclasses import asdict

    from bonesim.errors import BonesimError
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import load_model
    from bonesim.session.header import make_header
    from bonesim.runtime.simulate import run_trajectory

    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    if int(sessions) < 1:
        raise ValueError(f"sessions must be at least 1, got {sessions}")
    d_e, d_n, d_l = load_behaviours(behaviours) if behaviours is not None else \
        (ExpertModel(), NoviceModel(), Learning())
    expert = d_e if expert is None else expert
    novice = d_n if novice is None else novice
    learning = d_l if learning is None else learning
    people = draw_participants(experts, novices, seed, expert, novice)
    out = Path(out_dir)
    if out.is_dir() and any(out.glob("*.h5")):
        raise BonesimError(f"{out} already holds session files: give an empty folder")
    out.mkdir(parents=True, exist_ok=True)
    models = {g: load_model(case, m.burr) for g, m in (("expert", expert),
                                                       ("novice", novice))}
    paths, rows = [], []
    total = len(people) * int(sessions)
    for p0 in people:
        for k in range(1, int(sessions) + 1):
            p = session_participant(p0, k, learning)
            model = models[p.group]
            if p.group == "expert":
                traj = expert_trajectory(model.case, model.clearance, p, expert, duration_s,
                                         grid=model.grid)
            else:
                traj = novice_trajectory(model.case, model.grid, model.clearance, p, novice,
                                         duration_s)
            path = out / (f"{p.id}.h5" if sessions == 1 else f"{p.id}_s{k}.h5")
            extra = [load_burr(expert.fine_burr)] if p.group == "expert" else []
            run_trajectory(model, traj, surface=False, record=path, burrs=extra,
                           header=make_header(model, extra, participant=p.id,
                                              input_device="scripted",
                                              notes=f"synthetic test data (bonesim cohort "
                                              f"synth, seed {seed}, session {k})"))
            paths.append(path)
            rows.append([p.id, p.group, f"{p.instructor_score:.2f}", k, path.name])
            if progress is not None:
                progress(len(paths), total)
    with open(out / PARTICIPANTS_CSV, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["id", "group", "instructor_score", "session", "file"])
        wr.writerows(rows)
    from bonesim import __version__

    (out / "synthesis.json").write_text(json.dumps(
        {"bonesim_version": __version__, "seed": int(seed), "experts": experts, "novices": novices,
         "sessions": int(sessions), "case": str(case), "duration_s": float(duration_s),
         "behaviours": str(behaviours) if behaviours is not None else "class defaults",
         "expert": asdict(expert),
         "novice": asdict(novice), "learning": asdict(learning),
         "participants": [asdict(p) for p in people]}, indent=2, default=list) + "\n")
    (out / "README.txt").write_text(
        "Synthetic test data made by `bonesim cohort synth` (bonesim metrics.synth):\n"
        "scripted runs of expert-like and novice-like behaviour models, not people.\n"
        f"case {case}, {experts} experts, {novices} novices, {sessions} session(s) each, "
        f"{duration_s:g} s per run, seed {seed}; every parameter in synthesis.json.\n")
    return paths
