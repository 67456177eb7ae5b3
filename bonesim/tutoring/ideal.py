"""The ideal follower: the best following the tutoring law allows.

The trainee's device is driven by the tutoring law (:mod:`bonesim.tutoring.law`)::

    F = K_p (P_instructor - P_trainee) + F_instructor,   |F| <= F_max

A passive follower under it settles on the law's *target*
``P_instructor + F_instructor / K_p``, not on the instructor's tool: during
bone contact the instructor's force pushes it about ``|F_i| / K_p`` off the
tool (3.3 N / 0.2 N/mm = 16.5 mm), by the law's design. Its distance to the
tool is therefore bimodal (about 0.4 mm in free motion, about 16 mm in
contact) and its median jumps between the two with the share of contact in
the span scored; and anything that weakens the law (the simulated hand's
spring to its rest point, the join ramp's gain below 1) can bring a follower
*closer* to the tool by resisting the law. How well a follower does what the
law asks is its distance to the law's target, and the figures compared are
means (stable where a bimodal median is not).

:func:`ideal_follow` runs the law, with the same gain and cap, on an *ideal
follower*: a point mass whose servo ticks at exactly the nominal rate, with
no link delay (it sees the instructor's motion at each tick's own instant),
no lost or stale packets, the law's full gain from the first tick (no join
ramp) and no hand holding it (no spring to a rest point). The law has no
damping term and an undamped mass swings about its target, so the ideal is
the best of the documented point masses that differ only in damping
(``dampings_ns_per_mm`` of ``bonesim/data/tutoring.toml``; :func:`best_ideal`:
the least mean distance to the law's target on the same motion and ticks).
:func:`compare` scores it and the real follower at exactly the same instants
(the real servo's scored ticks) against the same reference, and re-runs the
ideal with each of the real session's handicaps alone (the link's delay, the
servo's own tick instants, the join ramp, the hand's spring) to say what
they add.

The follower's moving mass, its dampings and integration step are data
(``bonesim/data/tutoring.toml``, ``[ideal_follower]``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.net.tutor_protocol import KP_N_PER_MM, RECOVER_S, SERVO_HZ
from bonesim.tutoring.law import tutor_force

__all__ = ["InstructorLog", "TickLog", "IdealParams", "ideal_params", "ideal_follow",
           "best_ideal", "law_target", "error_summary", "tracking_vs_ideal", "HANDICAPS",
           "compare"]


class InstructorLog:
    """Preallocated ring of the instructor samples a trainee received (the
    last ``n``), each once: time on the instructor's clock [s], tool centre
    [mm], force [N] and when the trainee first held it (its clock [s]), for
    :func:`compare`."""

    def __init__(self, n: int = 1 << 16):
        if n & (n - 1):
            raise ValueError("InstructorLog: n must be a power of two")
        self.t = np.zeros(n)
        self.pos = np.zeros((n, 3))
        self.force = np.zeros((n, 3))
        self.seen = np.zeros(n)
        self.count = 0
        self.last_t = math.nan

    def add(self, t_s: float, pos_mm, force_n, seen_s: float = math.nan) -> None:
        """Log a sample unless it is the one logged last (same time);
        ``seen_s``: the trainee's clock when it was first held [s]."""
        if t_s == self.last_t:
            return
        i = self.count & (len(self.t) - 1)
        self.t[i] = t_s
        self.pos[i] = pos_mm
        self.force[i] = force_n
        self.seen[i] = seen_s
        self.count += 1
        self.last_t = t_s

    def arrays(self, seen: bool = False) -> tuple:
        """``(t_s, pos_mm, force_n)`` (and ``seen_s`` if ``seen``) in the
        order received, sorted by time (a reordered packet goes where it
        belongs)."""
        n = len(self.t)
        if self.count <= n:
            sl = np.arange(self.count)
        else:
            sl = (self.count + np.arange(n)) & (n - 1)
        t = self.t[sl]
        o = np.argsort(t, kind="stable")
        out = (t[o], self.pos[sl][o], self.force[sl][o])
        return out + (self.seen[sl][o],) if seen else out


class TickLog:
    """Preallocated ring of the trainee servo's ticks (the last ``n``): its
    clock [s], the device's position [mm] and whether the tick was scored
    (the link up and an instructor sample held), for :func:`compare`."""

    def __init__(self, n: int = 1 << 16):
        if n & (n - 1):
            raise ValueError("TickLog: n must be a power of two")
        self.t = np.zeros(n)
        self.pos = np.zeros((n, 3))
        self.scored = np.zeros(n, dtype=bool)
        self.count = 0

    def add(self, t_s: float, pos_mm, scored: bool) -> None:
        i = self.count & (len(self.t) - 1)
        self.t[i] = t_s
        self.pos[i] = pos_mm
        self.scored[i] = scored
        self.count += 1

    def arrays(self) -> tuple:
        """``(t_s, pos_mm, scored)`` in tick order."""
        n = len(self.t)
        sl = (np.arange(self.count) if self.count <= n
              else (self.count + np.arange(n)) & (n - 1))
        return self.t[sl], self.pos[sl], self.scored[sl]


class IdealParams:
    """The ideal follower's model (``[ideal_follower]`` of ``tutoring.toml``).

    Attributes
    ----------
    mass_kg : float
        Moving mass [kg].
    damping_ns_per_mm : float
        Viscous damping [N s/mm].
    dampings_ns_per_mm : tuple of float
        The dampings :func:`best_ideal` tries [N s/mm] (``damping_ns_per_mm``
        alone by default).
    max_substep_s : float
        Longest integration step [s].
    """

    def __init__(self, mass_kg: float, damping_ns_per_mm: float, max_substep_s: float,
                 dampings_ns_per_mm=()):
        self.dampings_ns_per_mm = tuple(float(b) for b in dampings_ns_per_mm) \
            or (float(damping_ns_per_mm),)
        if not (mass_kg > 0 and max_substep_s > 0 and damping_ns_per_mm >= 0
                and min(self.dampings_ns_per_mm) >= 0):
            raise ValueError("ideal follower: mass and sub-step must be positive, damping "
                             "non-negative")
        self.mass_kg = float(mass_kg)
        self.damping_ns_per_mm = float(damping_ns_per_mm)
        self.max_substep_s = float(max_substep_s)


def ideal_params(path=None) -> IdealParams:
    """The ideal follower's parameters from ``tutoring.toml`` (or ``path``)."""
    from pathlib import Path

    from bonesim.errors import BonesimError
    from bonesim.resources import data_path
    from bonesim.tomlfile import check_keys, get_number, read_toml

    path = Path(path) if path is not None else data_path("tutoring.toml")
    doc = read_toml(path)
    check_keys(doc, ("ideal_follower",), path, "top level", required=("ideal_follower",))
    d = doc["ideal_follower"]
    keys = ("mass_kg", "dampings_ns_per_mm", "max_substep_s")
    check_keys(d, keys, path, "ideal_follower", required=keys)
    w = "ideal_follower"
    bs = d["dampings_ns_per_mm"]
    if not isinstance(bs, list) or not bs:
        raise BonesimError("'dampings_ns_per_mm' must be a list of numbers", path, w)
    bs = [get_number({"d": b}, "d", path, f"{w}.dampings_ns_per_mm", minimum=0.0)
          for b in bs]
    return IdealParams(get_number(d, "mass_kg", path, w, minimum=1e-6), bs[0],
                       get_number(d, "max_substep_s", path, w, minimum=1e-7), bs)


def _motion(t, p, f):
    """Sample times with repeats removed (the last of each kept), checked."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(p, dtype=float)
    f = np.asarray(f, dtype=float)
    if t.ndim != 1 or p.shape != (len(t), 3) or f.shape != (len(t), 3):
        raise ValueError("ideal_follow: t_s (n,), pos_mm and force_n (n, 3)")
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0)):
        raise ValueError("ideal_follow: sample times must be finite and non-decreasing")
    last = np.r_[t[1:] != t[:-1], True] if len(t) else np.zeros(0, bool)
    return t[last], p[last], f[last]


def _at(t, v, q):
    """``v`` (n, 3) linear in ``t`` at the times ``q`` (held past the ends)."""
    return np.stack([np.interp(q, t, v[:, a]) for a in range(3)], axis=1)


def law_target(t_s, pos_mm, force_n, at_s, kp_n_per_mm: float = KP_N_PER_MM) -> np.ndarray:
    """Where the law holds a still follower: ``P_i + F_i / K_p`` at ``at_s``.

    Parameters
    ----------
    t_s : (n,) float
        Instructor sample times, non-decreasing [s].
    pos_mm, force_n : (n, 3) float
        Instructor tool centre [mm] and force [N] (linear between samples).
    at_s : (m,) float
        Instants [s].
    kp_n_per_mm : float
        The law's gain [N/mm] (positive).

    Returns
    -------
    (m, 3) float64
        The law's target [mm].
    """
    if not kp_n_per_mm > 0:
        raise ValueError("law_target: the gain must be positive")
    t, p, f = _motion(t_s, pos_mm, force_n)
    q = np.asarray(at_s, dtype=float)
    return _at(t, p, q) + _at(t, f, q) / kp_n_per_mm


def ideal_follow(t_s, pos_mm, force_n, kp_n_per_mm: float = KP_N_PER_MM,
                 max_force_n: float = 3.3, params: IdealParams | None = None,
                 rate_hz: float = SERVO_HZ, at_s=None, delay_s: float = 0.0,
                 ticks_s=None, ramp_s: float = 0.0,
                 stiffness_n_per_mm: float = 0.0) -> np.ndarray:
    """Positions of a follower of the law on an instructor's motion.

    With the defaults this is the ideal follower: servo ticks every
    ``1 / rate_hz`` from the first instant ``at_s[0]``; at each tick the
    instructor's motion at that instant (linear between samples, so that
    samples the link lost leave no steps; held past the last) gives
    ``P_instructor`` and ``F_instructor``, the law's force
    (:func:`tutor_force`, gain 1) is held until the next tick while the
    point mass, starting at rest on ``P_instructor(at_s[0])`` (as a hand
    picks up the stylus), moves (semi-implicit Euler in sub-steps of at most
    ``params.max_substep_s``, as :class:`~bonesim.devices.simulated_hand.SimulatedHandDevice`).
    The keyword handicaps give the followers it is compared with.

    Parameters
    ----------
    t_s : (n,) float
        Instructor sample times, non-decreasing [s] (the follower's clock).
    pos_mm : (n, 3) float
        Instructor tool centre, case frame [mm].
    force_n : (n, 3) float
        Force on the instructor's device [N].
    kp_n_per_mm, max_force_n : float
        The law's gain [N/mm] and force cap [N].
    params : IdealParams, optional
        Mass, damping (``params.damping_ns_per_mm``) and sub-step; default
        :func:`ideal_params`.
    rate_hz : float
        Servo rate [Hz] (when ``ticks_s`` is not given).
    at_s : (m,) float, optional
        Non-decreasing instants [s] to report the position at; default the
        ticks from ``t_s[0]`` to ``t_s[-1]``.
    delay_s : float
        Input delay [s]: each tick sees the motion at ``tick - delay_s``.
    ticks_s : (k,) float, optional
        The servo's tick instants [s] instead of the nominal grid (the
        first is the start).
    ramp_s : float
        The law's gain rises from 0 to 1 over this long [s] from the start.
    stiffness_n_per_mm : float
        A spring pulling the follower to its start point [N/mm] (a hand's).

    Returns
    -------
    (m, 3) float64
        The follower's position at each of ``at_s`` [mm].
    """
    t, p, f = _motion(t_s, pos_mm, force_n)
    if not (rate_hz > 0 and kp_n_per_mm >= 0 and max_force_n >= 0 and delay_s >= 0
            and ramp_s >= 0 and stiffness_n_per_mm >= 0):
        raise ValueError("ideal_follow: rate positive; gain, cap, delay, ramp and "
                         "stiffness non-negative")
    prm = ideal_params() if params is None else params
    if at_s is None:
        if len(t) == 0:
            return np.zeros((0, 3))
        at = t[0] + np.arange(int(math.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1) / rate_hz
    else:
        at = np.asarray(at_s, dtype=float)
    if len(at) == 0:
        return np.zeros((0, 3))
    if len(t) == 0:
        raise ValueError("ideal_follow: no instructor samples")
    if not (np.all(np.isfinite(at)) and np.all(np.diff(at) >= 0)):
        raise ValueError("ideal_follow: report instants must be finite and non-decreasing")
    if ticks_s is None:
        n_ticks = int(math.floor((at[-1] - at[0]) * rate_hz + 1e-9)) + 1
        ticks = at[0] + np.arange(n_ticks) / rate_hz
    else:
        ticks = np.asarray(ticks_s, dtype=float)
        if len(ticks) == 0 or np.any(np.diff(ticks) <= 0) or ticks[0] > at[0]:
            raise ValueError("ideal_follow: ticks must increase and start by the first "
                             "instant")
    seen_p = _at(t, p, ticks - delay_s)
    seen_f = _at(t, f, ticks - delay_s)
    out = np.zeros((len(at), 3))
    x0 = _at(t, p, ticks[:1] - delay_s)[0]
    _follow(ticks, seen_p, seen_f, at, float(kp_n_per_mm), float(max_force_n), float(ramp_s),
            1000.0 / prm.mass_kg, prm.damping_ns_per_mm, float(stiffness_n_per_mm),
            prm.max_substep_s, x0, out)
    return out


@njit(cache=True, nogil=True)
def _follow(ticks, seen_p, seen_f, at, kp, fmax, ramp_s, acc_per_n, b, k, hmax, x0, out):
    """:func:`ideal_follow`'s loop: ticks (k,), seen motion (k, 3), report
    instants (m,), x0 (3,) start [mm]; positions into ``out`` (m, 3)."""
    x = x0.copy()
    rest = x0.copy()
    v = np.zeros(3)
    force = np.zeros(3)
    now = ticks[0]
    j = 0
    m = at.shape[0]
    nt = ticks.shape[0]
    for i in range(nt):
        gain = 1.0
        if ramp_s > 0.0:
            gain = min(1.0, (ticks[i] - ticks[0]) / ramp_s)
        tutor_force(seen_p[i], x, seen_f[i], kp, fmax, gain, force)
        end = ticks[i + 1] if i + 1 < nt else np.inf
        while True:
            stop = end
            record = j < m and at[j] < end
            if record:
                stop = at[j]
            dt = stop - now
            if dt > 0.0 and dt < np.inf:
                n = int(math.ceil(dt / hmax))
                h = dt / n
                for _ in range(n):
                    for a in range(3):
                        v[a] += h * acc_per_n * (force[a] - b * v[a] - k * (x[a] - rest[a]))
                        x[a] += h * v[a]
                now = stop
            if not record:
                break
            for a in range(3):
                out[j, a] = x[a]
            j += 1
        if j == m:
            break


def best_ideal(t_s, pos_mm, force_n, at_s, kp_n_per_mm: float = KP_N_PER_MM,
               max_force_n: float = 3.3, params: IdealParams | None = None,
               rate_hz: float = SERVO_HZ) -> tuple:
    """The best ideal follower on this motion: :func:`ideal_follow` with
    each of ``params.dampings_ns_per_mm``, keeping the least mean distance
    to the law's target (:func:`law_target`) at ``at_s``.

    Returns
    -------
    pos : (m, 3) float64
        Its position at each of ``at_s`` [mm].
    damping_ns_per_mm : float
        Its damping [N s/mm] (NaN without instants).
    """
    prm = ideal_params() if params is None else params
    at = np.asarray(at_s, dtype=float)
    if len(at) == 0:
        return np.zeros((0, 3)), math.nan
    target = law_target(t_s, pos_mm, force_n, at, kp_n_per_mm)
    best, best_b, best_e = None, math.nan, math.inf
    for b in prm.dampings_ns_per_mm:
        one = IdealParams(prm.mass_kg, b, prm.max_substep_s)
        x = ideal_follow(t_s, pos_mm, force_n, kp_n_per_mm, max_force_n, one, rate_hz, at)
        e = float(np.mean(np.linalg.norm(target - x, axis=1)))
        if e < best_e:
            best, best_b, best_e = x, b, e
    return best, best_b


def error_summary(err_mm) -> dict:
    """``{"mean", "p50", "p95", "n"}`` of distances [mm] (``None`` figures
    when there are none)."""
    e = np.asarray(err_mm, dtype=float)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return {"mean": None, "p50": None, "p95": None, "n": 0}
    return {"mean": round(float(e.mean()), 3),
            "p50": round(float(np.percentile(e, 50)), 3),
            "p95": round(float(np.percentile(e, 95)), 3), "n": int(len(e))}


def tracking_vs_ideal(session_err_mm, ideal_err_mm) -> dict:
    """Two followers' distances side by side, scored at the same instants.

    Returns
    -------
    dict
        ``session`` and ``ideal`` (:func:`error_summary` [mm]),
        ``ratio_mean``, ``ratio_p50`` and ``ratio_p95`` (session / ideal;
        ``None`` if either is missing or the ideal's is zero).
    """
    s, i = error_summary(session_err_mm), error_summary(ideal_err_mm)

    def ratio(q):
        a, b = s[q], i[q]
        return None if a is None or not b else round(a / b, 3)

    return {"session": s, "ideal": i, "ratio_mean": ratio("mean"),
            "ratio_p50": ratio("p50"), "ratio_p95": ratio("p95")}


#: What :func:`compare` re-runs the ideal with, one at a time, and what each says.
HANDICAPS = {
    "link_delay": "the delay from the instructor's sample to the trainee's servo (the "
                  "instructor's simulation step, the server, the network; beyond the fastest "
                  "sample's)",
    "servo_ticks": "the trainee servo's own tick instants (late ticks hold the force longer)",
    "join_ramp": "the force fading in when the trainee joins",
    "hand": "the simulated hand's resistance (its damping and spring to its rest point)",
}


def compare(tick_s, device_mm, scored, instr_t_s, instr_pos_mm, instr_force_n, seen_s,
            kp_n_per_mm: float = KP_N_PER_MM, max_force_n: float = 3.3,
            speed: float = 1.0, params: IdealParams | None = None,
            rate_hz: float = SERVO_HZ, ramp_s: float = RECOVER_S, hand=None) -> dict:
    """A session's following beside the ideal follower's, at the same instants.

    The instructor's samples are put on the trainee's clock by the fastest
    delivery (``t / speed + min(seen - t / speed)``: no link delay; exact for
    a recording played back). The instants scored are the trainee servo's
    scored ticks within the samples' span; at each, both followers'
    distance to the instructor's tool and to the law's target
    (:func:`law_target`) are taken. The ideal is :func:`best_ideal`; then it
    is re-run, with its damping, under each handicap of :data:`HANDICAPS`
    alone (the hand only when ``hand`` is given), each reported as its mean
    distance to the law's target beside the ideal's.

    Parameters
    ----------
    tick_s : (k,) float
        The trainee servo's ticks, increasing (trainee clock [s]).
    device_mm : (k, 3) float
        The trainee device's position at each tick [mm].
    scored : (k,) bool
        Ticks with the link up and an instructor sample held.
    instr_t_s : (n,) float
        Instructor sample times, non-decreasing (instructor clock [s]).
    instr_pos_mm, instr_force_n : (n, 3) float
        Instructor tool centre [mm] and force [N].
    seen_s : (n,) float
        When the trainee first held each sample (trainee clock [s]).
    kp_n_per_mm, max_force_n : float
        The law's gain [N/mm] and force cap [N].
    speed : float
        Instructor seconds per trainee second (a playback's speed).
    params : IdealParams, optional
    rate_hz : float
        The servo's nominal rate [Hz].
    ramp_s : float
        How long the force fades in when the trainee joins [s].
    hand : tuple, optional
        ``(mass_kg, damping_ns_per_mm, stiffness_n_per_mm)`` of a simulated
        hand.

    Returns
    -------
    dict
        ``law_target`` and ``tool``: :func:`tracking_vs_ideal` of the
        distances to the law's target and to the tool; ``value``: the
        ratio of the mean distances to the law's target (session / ideal);
        ``span_s`` (first and last instant scored, trainee clock [s]),
        ``seconds``, ``damping_ns_per_mm`` (the ideal's), ``delay_ms``
        (link delay beyond the fastest: median and p95), ``late_ticks``
        (share of tick intervals over twice the nominal), ``handicaps``
        (name -> mean distance to the law's target [mm] with that handicap
        alone) and ``limited_by`` (the handicap adding most, or None).
    """
    prm = ideal_params() if params is None else params
    tick = np.asarray(tick_s, dtype=float)
    dev = np.asarray(device_mm, dtype=float)
    sc = np.asarray(scored, dtype=bool)
    t, p, f = (np.asarray(a, dtype=float) for a in (instr_t_s, instr_pos_mm, instr_force_n))
    seen = np.asarray(seen_s, dtype=float)
    if not speed > 0:
        raise ValueError("compare: speed must be positive")
    empty = {"law_target": tracking_vs_ideal([], []), "tool": tracking_vs_ideal([], []),
             "value": None, "span_s": None, "seconds": 0.0, "damping_ns_per_mm": None,
             "delay_ms": None, "late_ticks": None, "handicaps": {}, "limited_by": None}
    ok = np.isfinite(seen)
    if not ok.any() or not sc.any():
        return empty
    t, p, f, seen = t[ok], p[ok], f[ok], seen[ok]
    scaled = t / speed
    local = scaled + float(np.min(seen - scaled))       # the fastest delivery: no delay
    delay = seen - local
    at_mask = sc & (tick >= local[0])
    if not at_mask.any():
        return empty
    at = tick[at_mask]
    real = dev[at_mask]
    target = law_target(local, p, f, at, kp_n_per_mm)
    tool = _at(local, p, at)
    ideal, b = best_ideal(local, p, f, at, kp_n_per_mm, max_force_n, prm, rate_hz)

    def dist(a, x):
        return np.linalg.norm(a - x, axis=1)

    by_target = tracking_vs_ideal(dist(target, real), dist(target, ideal))
    out = {"law_target": by_target, "tool": tracking_vs_ideal(dist(tool, real), dist(tool, ideal)),
           "value": by_target["ratio_mean"],
           "span_s": [round(float(at[0]), 4), round(float(at[-1]), 4)],
           "seconds": round(float(at[-1] - at[0]), 3), "damping_ns_per_mm": b,
           "delay_ms": {"p50": round(float(np.median(delay)) * 1e3, 3),
                        "p95": round(float(np.percentile(delay, 95)) * 1e3, 3)}}
    run = tick[(tick >= at[0]) & (tick <= at[-1])]
    gaps = np.diff(run)
    out["late_ticks"] = round(float(np.mean(gaps > 2.0 / rate_hz)), 4) if len(gaps) else 0.0
    one = IdealParams(prm.mass_kg, b, prm.max_substep_s)
    runs = {"link_delay": dict(delay_s=float(np.median(delay))),
            "servo_ticks": dict(ticks_s=run),
            "join_ramp": dict(ramp_s=ramp_s)}
    if hand is not None:
        m, hb, hk = hand
        runs["hand"] = dict(stiffness_n_per_mm=hk,
                            params=IdealParams(m, hb, prm.max_substep_s))
    ideal_mean = by_target["ideal"]["mean"]
    hc = {}
    for name, kw in runs.items():
        kw = dict(kw)
        x = ideal_follow(local, p, f, kp_n_per_mm, max_force_n, kw.pop("params", one), rate_hz,
                         at, **kw)
        hc[name] = round(float(np.mean(dist(target, x))), 3)
    out["handicaps"] = hc
    worst = max(hc, key=hc.get) if hc else None
    out["limited_by"] = worst if worst is not None and ideal_mean is not None \
        and hc[worst] > ideal_mean else None
    return out
