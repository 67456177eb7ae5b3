"""The ideal follower: the best tracking the tutoring law allows.

The trainee's device is driven by the tutoring law (:mod:`bonesim.tutoring.law`)::

    F = K_p (P_instructor - P_trainee) + F_instructor,   |F| <= F_max

Even a perfect device and link cannot follow the instructor exactly under
it: the spring is weak by design (the trainee is guided gently), the
instructor's own force ``F_instructor`` is added (the bone's contact force
pushes the follower off the instructor's tool by about ``|F_i| / K_p``) and
the force cap limits the acceleration. :func:`ideal_follow` runs that law,
with the same gain and cap, on an *ideal follower*: a point mass with no
link delay (it sees each instructor sample at the instructor's own sample
time), no lost or stale packets, and no hand holding it (no spring to a
rest point). The law has no damping term and an undamped mass swings about
the instructor's tool, so the follower is the best of a few passive point
masses that differ only in their damping (:func:`best_ideal`: the least
median error on the same motion). Its tracking error is what the law alone accounts
for; a real session's error beside it (:func:`tracking_vs_ideal`) shows
what the link and the trainee's hand add.

The follower's moving mass and its integration step are data
(``bonesim/data/tutoring.toml``, ``[ideal_follower]``).
"""
from __future__ import annotations

import math

import numpy as np

from bonesim.net.tutor_protocol import KP_N_PER_MM, SERVO_HZ
from bonesim.tutoring.law import tutor_force

__all__ = ["InstructorLog", "IdealParams", "ideal_params", "ideal_follow", "best_ideal",
           "error_summary",
           "tracking_vs_ideal"]


class InstructorLog:
    """Preallocated ring of the instructor samples a trainee received (the
    last ``n``), each once: time on the instructor's clock [s], tool centre
    [mm] and force [N], for :func:`ideal_follow`."""

    def __init__(self, n: int = 1 << 16):
        if n & (n - 1):
            raise ValueError("InstructorLog: n must be a power of two")
        self.t = np.zeros(n)
        self.pos = np.zeros((n, 3))
        self.force = np.zeros((n, 3))
        self.count = 0
        self.last_t = math.nan

    def add(self, t_s: float, pos_mm, force_n) -> None:
        """Log a sample unless it is the one logged last (same time)."""
        if t_s == self.last_t:
            return
        i = self.count & (len(self.t) - 1)
        self.t[i] = t_s
        self.pos[i] = pos_mm
        self.force[i] = force_n
        self.count += 1
        self.last_t = t_s

    def arrays(self) -> tuple:
        """``(t_s, pos_mm, force_n)`` in the order received, sorted by time
        (a reordered packet goes where it belongs)."""
        n = len(self.t)
        if self.count <= n:
            sl = np.arange(self.count)
        else:
            sl = (self.count + np.arange(n)) & (n - 1)
        t = self.t[sl]
        o = np.argsort(t, kind="stable")
        return t[o], self.pos[sl][o], self.force[sl][o]


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


def ideal_follow(t_s, pos_mm, force_n, kp_n_per_mm: float = KP_N_PER_MM,
                 max_force_n: float = 3.3, params: IdealParams | None = None,
                 rate_hz: float = SERVO_HZ) -> np.ndarray:
    """Tracking error of the ideal follower on an instructor's samples.

    The follower starts at rest on the instructor's first position (as the
    trainee's hand picks up the stylus). Servo ticks come every
    ``1 / rate_hz`` from the first sample time to the last; at each tick the
    instructor's motion at that time (no delay; linear between samples, so
    that samples the link lost leave no steps) gives ``P_instructor`` and
    ``F_instructor``, the error ``|P_i - x|`` is taken,
    the law's force (link gain 1) is computed with :func:`tutor_force` and
    held while the point mass moves to the next tick (semi-implicit Euler).

    Parameters
    ----------
    t_s : (n,) float
        Instructor sample times, non-decreasing [s].
    pos_mm : (n, 3) float
        Instructor tool centre, case frame [mm].
    force_n : (n, 3) float
        Force on the instructor's device [N].
    kp_n_per_mm, max_force_n : float
        The law's gain [N/mm] and force cap [N].
    params : IdealParams, optional
        Default :func:`ideal_params`.
    rate_hz : float
        Servo rate [Hz].

    Returns
    -------
    (m,) float64
        Tracking error at each tick [mm].
    """
    t = np.asarray(t_s, dtype=float)
    p = np.asarray(pos_mm, dtype=float)
    f = np.asarray(force_n, dtype=float)
    if t.ndim != 1 or p.shape != (len(t), 3) or f.shape != (len(t), 3):
        raise ValueError("ideal_follow: t_s (n,), pos_mm and force_n (n, 3)")
    if len(t) == 0:
        return np.zeros(0)
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0)):
        raise ValueError("ideal_follow: sample times must be finite and non-decreasing")
    if not (rate_hz > 0 and kp_n_per_mm >= 0 and max_force_n >= 0):
        raise ValueError("ideal_follow: rate and cap positive, gain non-negative")
    prm = ideal_params() if params is None else params
    dt = 1.0 / rate_hz
    ticks = t[0] + dt * np.arange(int(math.floor((t[-1] - t[0]) / dt)) + 1)
    # the motion at each tick, linear between samples (repeated times: the last)
    last = np.r_[t[1:] != t[:-1], True]
    tu, pu, fu = t[last], p[last], f[last]
    pt = np.stack([np.interp(ticks, tu, pu[:, a]) for a in range(3)], axis=1)
    ft = np.stack([np.interp(ticks, tu, fu[:, a]) for a in range(3)], axis=1)
    n_sub = max(1, int(math.ceil(dt / prm.max_substep_s)))
    h = dt / n_sub
    acc_per_n = 1000.0 / prm.mass_kg                    # [mm/s^2 per N]
    b = prm.damping_ns_per_mm
    x = p[0].copy()
    v = np.zeros(3)
    out = np.zeros(3)
    err = np.empty(len(ticks))
    for k in range(len(ticks)):
        pi = pt[k]
        d = pi - x
        err[k] = math.sqrt(d @ d)
        tutor_force(pi, x, ft[k], kp_n_per_mm, max_force_n, 1.0, out)
        for _ in range(n_sub):
            v += h * acc_per_n * (out - b * v)
            x += h * v
    return err


def best_ideal(t_s, pos_mm, force_n, kp_n_per_mm: float = KP_N_PER_MM,
               max_force_n: float = 3.3, params: IdealParams | None = None,
               rate_hz: float = SERVO_HZ) -> tuple:
    """The best ideal follower on this motion: :func:`ideal_follow` with
    each of ``params.dampings_ns_per_mm``, keeping the least median error.

    Returns
    -------
    err : (m,) float64
        Its tracking error at each tick [mm].
    damping_ns_per_mm : float
        Its damping [N s/mm] (NaN without samples).
    """
    prm = ideal_params() if params is None else params
    best, best_b = np.zeros(0), math.nan
    for b in prm.dampings_ns_per_mm:
        one = IdealParams(prm.mass_kg, b, prm.max_substep_s)
        e = ideal_follow(t_s, pos_mm, force_n, kp_n_per_mm, max_force_n, one, rate_hz)
        if len(e) and (best_b != best_b or np.median(e) < np.median(best)):
            best, best_b = e, b
    return best, best_b


def error_summary(err_mm) -> dict:
    """``{"p50": median, "p95": ..., "n": ...}`` of tracking errors [mm]
    (``None`` figures when there are none)."""
    e = np.asarray(err_mm, dtype=float)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return {"p50": None, "p95": None, "n": 0}
    return {"p50": round(float(np.percentile(e, 50)), 3),
            "p95": round(float(np.percentile(e, 95)), 3), "n": int(len(e))}


def tracking_vs_ideal(session_err_mm, ideal_err_mm) -> dict:
    """The session's tracking error beside the ideal follower's.

    Returns
    -------
    dict
        ``session`` and ``ideal`` (:func:`error_summary` [mm]),
        ``ratio_p50`` and ``ratio_p95`` (session / ideal; ``None`` if
        either is missing or the ideal's is zero).
    """
    s, i = error_summary(session_err_mm), error_summary(ideal_err_mm)

    def ratio(q):
        a, b = s[q], i[q]
        return None if a is None or not b else round(a / b, 3)

    return {"session": s, "ideal": i, "ratio_p50": ratio("p50"), "ratio_p95": ratio("p95")}
