"""Haptic tutoring's control law: the trainee force and the link gain.

    F_trainee = K_p (P_instructor - P_trainee) + F_instructor

clamped to the trainee device's force limit (:func:`tutor_force`); the gain
falls to zero when the instructor's data stop and fades back in when they
return (:func:`link_gain`).
"""
from __future__ import annotations

import math

from numba import njit

from bonesim.net.tutor_protocol import LOSS_S, RAMP_S, RECOVER_S

__all__ = ["tutor_force", "link_gain"]


# ----------------------------------------------------------------- controller
@njit(cache=True, nogil=True)
def tutor_force(p_instr, p_trainee, f_instr, kp_n_per_mm, max_force_n, gain, out):
    """The trainee's force, in place (allocation-free).

    ``out = gain * (kp (p_instr - p_trainee) + f_instr)``, scaled down to
    ``max_force_n`` if longer; zero if any input is not finite.

    Parameters
    ----------
    p_instr, p_trainee : (3,) float64
        Instructor's and trainee's tool centres [mm].
    f_instr : (3,) float64
        Force the instructor's device renders [N].
    kp_n_per_mm : float
        Spring gain K_p [N/mm].
    max_force_n : float
        Trainee device's force limit [N].
    gain : float
        Link gain in [0, 1] (:func:`link_gain`).
    out : (3,) float64
        Receives the force [N].

    Returns
    -------
    float
        Magnitude of ``out`` [N].
    """
    s = 0.0
    for a in range(3):
        v = gain * (kp_n_per_mm * (p_instr[a] - p_trainee[a]) + f_instr[a])
        out[a] = v
        s += v * v
    n = math.sqrt(s)
    if not n <= max_force_n:                      # longer than allowed, or NaN
        if math.isfinite(n) and n > 0.0 and max_force_n >= 0.0:
            k = max_force_n / n
            for a in range(3):
                out[a] *= k
            return max_force_n
        for a in range(3):
            out[a] = 0.0
        return 0.0
    return n


def link_gain(age_s: float, prev_gain: float, dt_s: float) -> float:
    """Force gain from the age of the freshest valid data.

    1 while the data is younger than :data:`LOSS_S`, then falling linearly to
    0 over :data:`RAMP_S`; after a loss it rises back by ``dt_s / RECOVER_S``
    per tick, never above the ramp.

    Parameters
    ----------
    age_s : float
        Time since the last valid data [s] (``inf`` if none yet).
    prev_gain : float
        The previous tick's gain.
    dt_s : float
        Time since the previous tick [s].
    """
    if age_s <= LOSS_S:
        ramp = 1.0
    elif age_s < LOSS_S + RAMP_S:
        ramp = (LOSS_S + RAMP_S - age_s) / RAMP_S
    else:
        ramp = 0.0                                    # also NaN ages
    up = prev_gain + max(dt_s, 0.0) / RECOVER_S
    return ramp if ramp < up else (up if up < 1.0 else 1.0)
