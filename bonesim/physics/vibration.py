"""Drill vibration synthesized at the haptic rate.

A real drill shakes the hand at its rotation frequency: the recorded peaks
are ~1 kHz (cutting burr: 1030 Hz free running, 875 Hz in bone contact;
diamond burr: 1049 Hz / 625 Hz). A haptic loop running at ``rate_hz``
(~1 kHz) can only carry frequencies below its Nyquist frequency
``rate_hz / 2``; rendering the peaks themselves would fold them back to
spurious low tones (1030 Hz sampled at 1 kHz is a 30 Hz rumble). We
therefore render only low-frequency *components* tied to the peaks, and keep
the variation that depends on the burr, the contact state and the force.

Components
----------
Each burr file lists ``vib_harmonics``: ``(freq_hz, rel_amp)`` pairs measured
in bone contact (the shipped files hold the 1/2, 1/3 and 1/4 subharmonics of
the contact peak, rounded: 291.7 Hz for 875/3). The *free-running* set is
derived from them the way the file's were made: a component within
``SUBHARMONIC_TOL`` (relative) of a 1/n subharmonic of the contact peak
becomes the exact 1/n subharmonic of the free peak; any other component keeps
its ratio to the main peak::

    f_free_k = vib_free_hz / n                      if f_k ~ vib_contact_hz / n
    f_free_k = f_k * vib_free_hz / vib_contact_hz   otherwise
    rel_free_k = rel_k

(1030/2, 1030/3, 1030/4 Hz for a cutting burr). Both sets
scale with the drill speed (``f * speed / default_speed``: the peaks are the
rotation rate). A component is rendered only while its current frequency is
below ``NYQUIST_FRACTION * rate_hz / 2``; the others are skipped (listed in
:attr:`Vibration.skipped` for the default speed). At 1 kHz this drops the
free 1/2 subharmonics (515 Hz and 524.5 Hz).

Force
-----
With ``|F|`` the applied force [N] and ``phi = speed / default_speed``
(clamped to ``[0, max_speed / default_speed]``), the amplitude is::

    A = (vib_amp_n + vib_amp_per_n * |F|) * phi          [N]

and component ``k`` of the active set is a vector of length ``A * rel_k``
rotating at ``f_k`` in the plane perpendicular to the drill axis ``d``
(an unbalanced head pushes radially): with ``(u, v)`` an orthonormal basis
of that plane and ``p_k`` the component's phase [cycles]::

    F_vib = sum_k A rel_k (cos(2 pi p_k) u + sin(2 pi p_k) v)

Phases are accumulated (``p_k += f_k dt``), so frequency changes never jump
the waveform, and start from values drawn from a seeded generator
(deterministic). The free and contact sets each have an envelope that ramps
linearly toward 1 (active) or 0 over ``RAMP_S`` as the contact state
changes, so switching sets does not jolt the device. With the drill off (or
at zero speed) both envelopes fall to exactly 0 within ``RAMP_S``.

Use in the haptic loop (after :func:`bonesim.engine.model.step`)::

    vib = Vibration(model.burr, model.haptic_rate_hz)
    ...
    force = step(model, state, sample)
    force += vib.sample(sample.t_s, state.axis, sample.drill,
                        state.out[O_N_IMMERSED] > 0, state.out[O_MAG],
                        sample.speed_rpm)

(``O_N_IMMERSED``, ``O_MAG`` from :mod:`bonesim.engine.haptics`). Make a new
:class:`Vibration` when the burr changes; the caller clamps the total to the
device's maximum force if it needs to.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.kernel_args import filled

__all__ = ["NYQUIST_FRACTION", "SUBHARMONIC_TOL", "RAMP_S", "MAX_DT_S", "Vibration",
           "vibration_signal", "free_components", "contact_components", "warmup"]

#: Components are rendered only below this fraction of the Nyquist frequency,
#: so none sits at Nyquist, where a sampled sine's amplitude depends on phase.
NYQUIST_FRACTION = 0.95
#: Relative tolerance within which a file component counts as a 1/n
#: subharmonic of the contact peak (the files round to 0.1 Hz or so).
SUBHARMONIC_TOL = 0.005
#: Time for an envelope to go from 0 to 1 (or back) when the contact state or
#: the drill switches [s].
RAMP_S = 0.005
#: Longest time step the envelopes advance by in one sample [s] (a stalled
#: loop must not be treated as a long silence).
MAX_DT_S = 0.05
# Component sets: index 0 free running, 1 in contact.
_FREE, _CONTACT = 0, 1
# Layout of the float64 state vector: time of the last sample, envelopes.
_S_LAST_T, _S_ENV_FREE, _S_ENV_CONTACT = range(3)
_N_STATE = 3
_TWO_PI = 2.0 * math.pi


def contact_components(burr) -> list[tuple[float, float]]:
    """In-contact components ``(freq_hz, rel_amp)`` at the default speed.

    These are the burr's ``vib_harmonics`` as written in its file.
    """
    return [(float(f), float(a)) for f, a in burr.vib_harmonics]


def free_components(burr) -> list[tuple[float, float]]:
    """Free-running components ``(freq_hz, rel_amp)`` at the default speed.

    An in-contact component at (about) ``vib_contact_hz / n`` becomes
    ``vib_free_hz / n``; any other keeps its ratio to the main peak,
    ``f * vib_free_hz / vib_contact_hz`` (see the module docstring).
    """
    free_hz, contact_hz = float(burr.vib_free_hz), float(burr.vib_contact_hz)
    out = []
    for f, a in contact_components(burr):
        n = round(contact_hz / f)
        if n >= 1 and abs(contact_hz / n - f) <= SUBHARMONIC_TOL * f:
            out.append((free_hz / n, a))
        else:
            out.append((f * free_hz / contact_hz, a))
    return out


@njit(cache=True, nogil=True, inline="always")
def _basis(axis):
    """Orthonormal ``(u, v)`` perpendicular to ``axis`` (any non-zero length)."""
    n = math.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2])
    dx, dy, dz = axis[0] / n, axis[1] / n, axis[2] / n
    if abs(dx) < 0.9:
        ex, ey, ez = 1.0, 0.0, 0.0
    else:
        ex, ey, ez = 0.0, 1.0, 0.0
    # u = e x d, normalized; v = d x u
    ux, uy, uz = ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx
    m = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / m, uy / m, uz / m
    vx, vy, vz = dy * uz - dz * uy, dz * ux - dx * uz, dx * uy - dy * ux
    return ux, uy, uz, vx, vy, vz


@njit(cache=True, nogil=True, inline="always")
def _vib_one(freq, rel, phase, state, t, contact, force, drill, phi, amp0, amp_per_n,
             limit_hz, default_dt):
    """Advance the synthesizer to time ``t`` [s]; return the in-plane
    components ``(c_u, c_v)`` [N]."""
    last = state[_S_LAST_T]
    if last == last and t >= last:       # not NaN and not going back
        dt = t - last
    else:
        dt = default_dt
    state[_S_LAST_T] = t
    running = drill and phi > 0.0
    step = min(dt, MAX_DT_S) / RAMP_S
    # envelopes ramp linearly toward their targets
    for s in range(2):
        target = 1.0 if running and (contact == (s == _CONTACT)) else 0.0
        e = state[_S_ENV_FREE + s]
        if e < target:
            e = min(target, e + step)
        elif e > target:
            e = max(target, e - step)
        state[_S_ENV_FREE + s] = e
    amp = (amp0 + amp_per_n * abs(force)) * phi
    cu = 0.0
    cv = 0.0
    for s in range(2):
        e = state[_S_ENV_FREE + s]
        for k in range(freq.shape[1]):
            f = freq[s, k] * phi
            p = phase[s, k] + f * dt
            p -= math.floor(p)
            phase[s, k] = p
            if e > 0.0 and 0.0 < f < limit_hz:
                a = amp * e * rel[s, k]
                w = _TWO_PI * p
                cu += a * math.cos(w)
                cv += a * math.sin(w)
    return cu, cv


@njit(cache=True, nogil=True)
def vibration_kernel(freq, rel, phase, state, t, contact, force, drill, phi, axis, amp0,
                     amp_per_n, limit_hz, default_dt, out):
    """Vibration force of one haptic sample, written to ``out`` (3,) [N].

    Parameters
    ----------
    freq, rel : (2, K) float64
        Component frequencies at the default speed [Hz] and relative
        amplitudes; row 0 free running, row 1 in contact (padding: rel 0).
    phase : (2, K) float64
        Component phases [cycles], advanced in place.
    state : (3,) float64
        Last time [s] (NaN before the first sample) and the two envelopes.
    t : float
        Sample time [s].
    contact, drill : bool
        Burr in contact with tissue; drill running.
    force : float
        Applied force magnitude [N].
    phi : float
        Speed relative to the burr's default speed (clamped by the caller).
    axis : (3,) float64
        Drill axis (non-zero).
    amp0, amp_per_n : float
        Base amplitude [N] and its growth per newton [N/N].
    limit_hz : float
        Components at or above this frequency are not rendered [Hz].
    default_dt : float
        Step used for the first sample or when time goes back [s].
    out : (3,) float64
        Receives the force [N].
    """
    cu, cv = _vib_one(freq, rel, phase, state, t, contact, force, drill, phi, amp0,
                      amp_per_n, limit_hz, default_dt)
    ux, uy, uz, vx, vy, vz = _basis(axis)
    out[0] = cu * ux + cv * vx
    out[1] = cu * uy + cv * vy
    out[2] = cu * uz + cv * vz


@njit(cache=True, nogil=True)
def vibration_series_kernel(freq, rel, phase, state, t, contact, force, drill, phi, axis,
                            amp0, amp_per_n, limit_hz, default_dt, out):
    """:func:`vibration_kernel` over ``n`` samples (arrays ``t, contact,
    force, drill, phi`` of length ``n``; ``out`` (n, 3))."""
    ux, uy, uz, vx, vy, vz = _basis(axis)
    for q in range(t.shape[0]):
        cu, cv = _vib_one(freq, rel, phase, state, t[q], contact[q], force[q], drill[q],
                          phi[q], amp0, amp_per_n, limit_hz, default_dt)
        out[q, 0] = cu * ux + cv * vx
        out[q, 1] = cu * uy + cv * vy
        out[q, 2] = cu * uz + cv * vz


class Vibration:
    """Per-burr vibration synthesizer for a haptic loop.

    Parameters
    ----------
    burr : Burr
        Reads ``vib_free_hz``, ``vib_contact_hz``, ``vib_amp_n``,
        ``vib_amp_per_n``, ``vib_harmonics``, ``default_speed_rpm`` and
        ``max_speed_rpm``.
    rate_hz : float
        Haptic loop rate [Hz]; sets the Nyquist limit of what is rendered.
    seed : int
        Seed of the components' start phases.

    Attributes
    ----------
    limit_hz : float
        Highest frequency rendered, ``NYQUIST_FRACTION * rate_hz / 2`` [Hz].
    free, contact : list of (float, float)
        Rendered components ``(freq_hz, rel_amp)`` at the default speed.
    skipped : list of (str, float, float)
        Components above :attr:`limit_hz` at the default speed, as
        ``("free" | "contact", freq_hz, rel_amp)``.
    """

    def __init__(self, burr, rate_hz: float = 1000.0, seed: int = 0):
        rate_hz = float(rate_hz)
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
        self.burr = burr
        self.rate_hz = rate_hz
        self.seed = int(seed)
        self.limit_hz = NYQUIST_FRACTION * rate_hz / 2.0
        sets = (free_components(burr), contact_components(burr))
        k = max(1, max(len(s) for s in sets))
        self._freq = np.zeros((2, k))
        self._rel = np.zeros((2, k))
        for s, comps in enumerate(sets):
            for j, (f, a) in enumerate(comps):
                self._freq[s, j], self._rel[s, j] = f, a
        names = ("free", "contact")
        self.skipped = [(names[s], f, a) for s, comps in enumerate(sets)
                        for f, a in comps if not f < self.limit_hz]
        self.free = [(f, a) for f, a in sets[0] if f < self.limit_hz]
        self.contact = [(f, a) for f, a in sets[1] if f < self.limit_hz]
        self._amp0 = float(burr.vib_amp_n)
        self._amp_per_n = float(burr.vib_amp_per_n)
        self._default_rpm = float(burr.default_speed_rpm)
        self._max_phi = float(burr.max_speed_rpm) / self._default_rpm
        self._phase = np.zeros((2, k))
        self._state = np.zeros(_N_STATE)
        self._axis = np.zeros(3)
        self._out = np.zeros(3)
        self.reset()

    def reset(self) -> None:
        """Back to the start: seeded phases, envelopes at 0, no previous time."""
        rng = np.random.default_rng(self.seed)
        self._phase[:] = rng.random(self._phase.shape)
        self._state[:] = 0.0
        self._state[_S_LAST_T] = math.nan

    def speed_factor(self, speed_rpm: float) -> float:
        """``speed / default_speed`` clamped to ``[0, max / default]``."""
        return min(max(float(speed_rpm), 0.0) / self._default_rpm, self._max_phi)

    def sample(self, t_s: float, axis, drill: bool, in_contact: bool, force_n: float,
               speed_rpm: float) -> np.ndarray:
        """Vibration force for the haptic sample at ``t_s``.

        Parameters
        ----------
        t_s : float
            Sample time [s] (non-decreasing between calls; a step back is
            treated as one nominal period ``1 / rate_hz``).
        axis : (3,) array_like
            Drill axis (any non-zero length).
        drill : bool
            Drill running.
        in_contact : bool
            Burr touching tissue (e.g. ``state.out[O_N_IMMERSED] > 0``).
        force_n : float
            Applied force magnitude [N].
        speed_rpm : float
            Drill speed [rpm].

        Returns
        -------
        (3,) float64
            Force to add to the device force [N]. The same array is reused
            (overwritten) by the next call: copy it to keep it.
        """
        ax = self._axis
        ax[0], ax[1], ax[2] = axis[0], axis[1], axis[2]
        if not (ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2]) > 0.0:
            raise ValueError("axis must be non-zero")
        vibration_kernel(self._freq, self._rel, self._phase, self._state, float(t_s),
                         bool(in_contact), float(force_n), bool(drill),
                         self.speed_factor(speed_rpm), ax, self._amp0, self._amp_per_n,
                         self.limit_hz, 1.0 / self.rate_hz, self._out)
        return self._out

    def series(self, t, contact, force, drill, speed, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
        """Run the synthesizer over ``n`` samples (continuing from its state).

        Same arguments as :func:`vibration_signal` minus the burr and rate.
        Returns an (n, 3) float64 array [N], equal to calling :meth:`sample`
        for each sample in turn.
        """
        t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1)
        n = t.shape[0]

        def col(x, dtype, name):
            a = filled(x, (n,), dtype)
            if dtype is np.float64 and not np.isfinite(a).all():
                raise ValueError(f"{name} must be finite")
            return a

        if not np.isfinite(t).all():
            raise ValueError("t must be finite")
        contact = col(contact, np.bool_, "contact")
        drill = col(drill, np.bool_, "drill")
        force = col(force, np.float64, "force")
        speed = col(speed, np.float64, "speed")
        phi = np.minimum(np.maximum(speed, 0.0) / self._default_rpm, self._max_phi)
        ax = np.asarray(axis, dtype=np.float64).reshape(3)
        if not np.isfinite(ax).all() or not np.dot(ax, ax) > 0:
            raise ValueError("axis must be finite and non-zero")
        out = np.zeros((n, 3))
        vibration_series_kernel(self._freq, self._rel, self._phase, self._state, t, contact,
                                force, drill, phi, ax, self._amp0, self._amp_per_n,
                                self.limit_hz, 1.0 / self.rate_hz, out)
        return out


def vibration_signal(burr, t, contact, force, drill, speed, rate_hz: float = 1000.0,
                     axis=(0.0, 0.0, 1.0), seed: int = 0) -> np.ndarray:
    """Vibration force over a scripted run (for analysis and tests).

    Parameters
    ----------
    burr : Burr
    t : (n,) array_like
        Sample times [s], non-decreasing (normally ``arange(n) / rate_hz``).
    contact : (n,) array_like of bool
        Burr touching tissue per sample (scalars broadcast).
    force : (n,) array_like
        Applied force magnitude [N].
    drill : (n,) array_like of bool
        Drill running.
    speed : (n,) array_like
        Drill speed [rpm].
    rate_hz : float
        Haptic rate [Hz] (sets which components are rendered).
    axis : (3,) array_like
        Drill axis, fixed over the run.
    seed : int
        Phase seed.

    Returns
    -------
    (n, 3) float64
        Vibration force [N], perpendicular to ``axis``; identical to a fresh
        :class:`Vibration` fed the same samples one by one.
    """
    return Vibration(burr, rate_hz, seed).series(t, contact, force, drill, speed, axis)


def warmup() -> None:
    """Compile the vibration kernels (cached on disk after the first run)."""
    from types import SimpleNamespace

    burr = SimpleNamespace(vib_free_hz=1000.0, vib_contact_hz=800.0, vib_amp_n=0.04,
                           vib_amp_per_n=0.03, vib_harmonics=((400.0, 0.5),),
                           default_speed_rpm=60000.0, max_speed_rpm=80000.0)
    v = Vibration(burr, 1000.0)
    v.sample(0.0, (0.0, 0.0, 1.0), True, True, 1.0, 60000.0)
    v.series(np.arange(4) / 1000.0, True, 1.0, True, 60000.0)
