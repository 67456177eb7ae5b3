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
    them, and per-participant region, layer depth, feed and margin.
Novice-like (:class:`NoviceModel`)
    Deep narrow holes with a smaller burr: a plunge along the line of sight
    at a steady fast feed down to a small margin from the structures beneath
    (some participants overshoot: an injury), then a sideways sweep at depth
    that undercuts the rim (removals hidden from the eye), back, and out;
    hole after hole around the focal axis.

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

__all__ = ["ExpertModel", "NoviceModel", "Participant", "draw_participants",
           "expert_trajectory", "novice_trajectory", "synth_cohort", "PARTICIPANTS_CSV",
           "SCORE_RANGE"]

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
    slow_within_mm: float = 12.0
    slow_share: float = 0.15
    fine_burr: str = "diamond-4mm"
    fine_within_mm: float = 3.0
    score: float = 4.06
    score_sd: float = 0.35


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
    """

    burr: str = "cutting-3mm"
    spread_mm: float = 5.0
    plunge_mm_s: float = 6.0
    plunge_sd_mm_s: float = 1.0
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
                      model: ExpertModel = ExpertModel(), duration_s: float | None = None):
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

    Returns
    -------
    bonesim.io.trajectory.Trajectory
        Burr centres [mm], case frame; cut at ``duration_s`` [s] if given.
    """
    from bonesim.io.toolpath import demo_trajectory, load_demo_plan

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
    traj = _slow_near_structures(demo_trajectory(moved, model.burr, plan), case, clearance,
                                 plan.margin_mm, model)
    return traj if duration_s is None else traj.at_times(traj.t_s[traj.t_s <= duration_s])


def _slow_near_structures(traj, case, clearance, margin_mm, model):
    """``traj`` retimed and with its burr stages: each drilling step takes
    ``1 / f`` as long, ``f`` falling linearly from 1 (burr surface
    ``margin + slow_within_mm`` from a structure) to ``slow_share`` (at the
    margin); a drilling pass that comes within ``fine_within_mm`` of the
    margin uses the fine burr (burr 1), changed while the drill rests before
    it."""
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
    burr = _burr_stages(traj.drill, gap - margin_mm, model.fine_within_mm)
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

    overshoot = rng.random() < model.overshoot_p * (1.0 - 0.3 * np.tanh(s))
    margin = -model.overshoot_mm if overshoot else max(
        0.05, model.margin_mm + model.margin_sd_mm * (0.5 * s + rng.standard_normal()))
    plunge = max(2.0, model.plunge_mm_s + model.plunge_sd_mm_s * rng.standard_normal())
    step = 0.1                                         # plan resolution [mm]
    above = 2.0 * r                                    # start this far above the bone [mm]
    path = None
    holes = misses = 0
    while True:
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
        length = max(0.5, model.undercut_mm + model.undercut_sd_mm * rng.standard_normal())
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
                 expert: ExpertModel = ExpertModel(), novice: NoviceModel = NoviceModel(),
                 progress=None) -> list[Path]:
    """Record a synthetic cohort into ``out_dir`` (module docstring).

    Writes ``<id>.h5`` per participant (the header names the participant,
    not the group), ``participants.csv`` (``id, group, instructor_score``)
    and a ``README.txt`` saying that the data are synthetic.

    Parameters
    ----------
    out_dir : path
        A folder that holds no session files yet (created if missing).
    experts, novices : int
        Participants per group, one run each.
    seed : int
        Seed of every draw.
    case : str
        Case name or ``case.toml`` path.
    duration_s : float
        Length of each run [s] (simulated time, at the haptic rate).
    progress : callable, optional
        Called with ``(done, total)`` after each run.

    Returns
    -------
    list of Path
        The session files, in participant order.
    """
    from bonesim.errors import BonesimError
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import load_model
    from bonesim.runtime.record import make_header
    from bonesim.runtime.simulate import run_trajectory

    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    people = draw_participants(experts, novices, seed, expert, novice)
    out = Path(out_dir)
    if out.is_dir() and any(out.glob("*.h5")):
        raise BonesimError(f"{out} already holds session files: give an empty folder")
    out.mkdir(parents=True, exist_ok=True)
    models = {g: load_model(case, m.burr) for g, m in (("expert", expert),
                                                       ("novice", novice))}
    paths = []
    for q, p in enumerate(people):
        model = models[p.group]
        if p.group == "expert":
            traj = expert_trajectory(model.case, model.clearance, p, expert, duration_s)
        else:
            traj = novice_trajectory(model.case, model.grid, model.clearance, p, novice,
                                     duration_s)
        path = out / f"{p.id}.h5"
        extra = [load_burr(expert.fine_burr)] if p.group == "expert" else []
        run_trajectory(model, traj, surface=False, record=path, burrs=extra,
                       header=make_header(model, extra, participant=p.id,
                                          input_device="scripted",
                                          notes="synthetic test data (bonesim cohort synth)"))
        paths.append(path)
        if progress is not None:
            progress(q + 1, len(people))
    with open(out / PARTICIPANTS_CSV, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["id", "group", "instructor_score"])
        for p in people:
            wr.writerow([p.id, p.group, f"{p.instructor_score:.2f}"])
    (out / "README.txt").write_text(
        "Synthetic test data made by `bonesim cohort synth` (bonesim metrics.synth):\n"
        "scripted runs of expert-like and novice-like behaviour models, not people.\n"
        f"case {case}, {experts} experts, {novices} novices, {duration_s:g} s each, "
        f"seed {seed}.\n")
    return paths
