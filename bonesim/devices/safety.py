"""The safety and fault layer every real device runs behind (CHAI3D's habits).

:class:`SafeDevice` wraps any backend (:class:`~bonesim.devices.interface.Device`)
and is itself one, so the haptic loop drives it like any other:

Safe start
    Forces stay off until the hand has stayed within
    :attr:`SafetyLimits.still_radius_mm` for :attr:`SafetyLimits.still_for_s`
    with the commanded force below :attr:`SafetyLimits.start_force_n`; then the
    force is ramped in linearly over :attr:`SafetyLimits.ramp_s`.
Limits
    The rendered force never exceeds the device's ``caps.max_force_n``, and its
    magnitude may grow by at most ``caps.max_stiffness_n_per_mm`` times the
    hand's motion since the previous sample (plus a small slew allowance,
    :attr:`SafetyLimits.slew_n_per_s`, so that forces can build while the
    hand holds still): the stiffness the hand feels is bounded by the
    device's record whatever the bone's. Decreases pass at once.
Bad samples
    A reading with a NaN or infinite pose, a jump between two samples larger
    than the device's workspace along any axis, or a timestamp older than
    :attr:`SafetyLimits.stale_s` (or going backwards) is rejected and counted
    (:attr:`SafeDevice.rejected`, per reason); the previous pose holds. After
    :attr:`SafetyLimits.resync_samples` jumps in a row the new pose is taken
    as real and the safe start begins again.
Unplugging
    A backend that raises :class:`~bonesim.devices.interface.DeviceDisconnected`
    (or any ``OSError``) from ``read`` or ``write_force`` is unplugged: the
    force goes to zero at once, the ``fallback`` device (the mouse) takes over
    (:attr:`SafeDevice.coupled` tells the loop to put it through its virtual
    coupling), and the backend's ``open`` is retried every
    :attr:`SafetyLimits.reconnect_s`. When it succeeds the device resumes
    after the safe start. :attr:`SafeDevice.state` (one of :data:`STATES`) is
    what the loop publishes for the HUD and the recording.

Nothing here allocates in :meth:`SafeDevice.read` / :meth:`SafeDevice.write_force`
on the normal path apart from the backend's own reading.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bonesim.devices.interface import DeviceDisconnected, DeviceReading, unit_axis
from bonesim.errors import BonesimError

__all__ = ["ACTIVE", "WAITING", "RAMPING", "UNPLUGGED", "STATES", "REJECT_REASONS",
           "SafetyLimits", "SafeDevice"]

#: Device states (:attr:`SafeDevice.state`): forces on; safe start, waiting
#: for a still hand and a small force; ramping forces in; unplugged (the
#: fallback drives the tool).
ACTIVE, WAITING, RAMPING, UNPLUGGED = range(4)
STATES = ("active", "waiting", "ramping", "unplugged")
#: Why a sample was rejected (keys of :attr:`SafeDevice.rejected`).
REJECT_REASONS = ("nan", "jump", "stale")


@dataclass(frozen=True)
class SafetyLimits:
    """The safety layer's thresholds.

    Attributes
    ----------
    still_radius_mm : float
        The hand counts as still while it stays within this distance of
        where it settled [mm].
    still_for_s : float
        ... for this long, with a small commanded force, before forces start [s].
    start_force_n : float
        Largest commanded force at which forces may start [N].
    ramp_s : float
        Forces ramp from zero to full over this time [s].
    stale_s : float
        A reading measured longer ago than this is stale [s].
    reconnect_s : float
        An unplugged device is looked for again this often [s].
    resync_samples : int
        Jumps in a row after which the new pose is taken as real.
    slew_n_per_s : float
        How fast the force may grow while the hand holds still [N/s].
    """

    still_radius_mm: float = 1.0
    still_for_s: float = 0.3
    start_force_n: float = 0.3
    ramp_s: float = 1.0
    stale_s: float = 0.05
    reconnect_s: float = 0.5
    resync_samples: int = 50
    slew_n_per_s: float = 200.0

    def __post_init__(self):
        for k in ("still_radius_mm", "still_for_s", "start_force_n", "ramp_s", "stale_s",
                  "reconnect_s", "resync_samples"):
            if not getattr(self, k) > 0:
                raise ValueError(f"safety limit {k} must be positive")
        if not self.slew_n_per_s >= 0:
            raise ValueError("safety limit slew_n_per_s must be non-negative")


class SafeDevice:
    """A backend behind the safety and fault layer (module docstring).

    Parameters
    ----------
    device : Device
        The backend.
    fallback : Device, optional
        Drives the tool while ``device`` is unplugged (the mouse). Without
        one the last good pose holds.
    limits : SafetyLimits

    Attributes
    ----------
    state : int
        One of :data:`STATES` (index).
    rejected : dict of str -> int
        Rejected samples per reason (:data:`REJECT_REASONS`).
    unplugs, replugs : int
        Times the device went away and came back.
    sent_n : (3,) float64
        The force last sent to the device [N] (zero while unplugged).
    gain : float
        The ramp's gain in [0, 1] last applied.
    """

    def __init__(self, device, fallback=None, limits: SafetyLimits = SafetyLimits()):
        self.device = device
        self.fallback = fallback
        self.limits = limits
        self.state = WAITING
        self.rejected = {k: 0 for k in REJECT_REASONS}
        self.unplugs = 0
        self.replugs = 0
        self.sent_n = np.zeros(3)
        self.gain = 0.0
        self._limited = np.zeros(3)
        self._held: DeviceReading | None = None
        self._t = 0.0
        self._dx_mm = 0.0
        self._dt_s = 0.0
        self._jumps = 0
        self._last_ts = -math.inf
        self._anchor = np.zeros(3)
        self._still_since = math.nan
        self._ramp_from = math.nan
        self._retry_at = 0.0
        self._events: list = []

    # -------------------------------------------------------------- state
    @property
    def caps(self):
        """The backend's record (a device may read its own when opened)."""
        return self.device.caps

    @property
    def state_name(self) -> str:
        return STATES[self.state]

    @property
    def renders(self) -> bool:
        """The device renders force (a finite ``caps.max_force_n``)."""
        return math.isfinite(self.caps.max_force_n)

    @property
    def coupled(self) -> bool:
        """The reading is a target for the loop's virtual coupling: the
        fallback drives, or the device renders no force (a rate device)."""
        return (self.state == UNPLUGGED and self.fallback is not None) or not self.renders

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def take_events(self) -> list:
        """``(t_s, what)`` transitions since the last call (``unplugged``,
        ``replugged``, ``forces-on``, ``resync``); for recording."""
        ev, self._events = self._events, []
        return ev

    def _restart(self, t: float) -> None:
        """Forces off; wait for a still hand, then ramp (a device that
        renders no force is active at once)."""
        self.state = WAITING if self.renders else ACTIVE
        self.gain = 0.0
        self._still_since = t
        self._ramp_from = math.nan
        if self._held is not None:
            self._anchor[:] = self._held.pos_mm

    # --------------------------------------------------------- interface
    def open(self) -> None:
        """Open the backend (its error propagates: the user asked for it)."""
        self.device.open()
        if self.fallback is not None:
            self.fallback.open()
        self._restart(0.0)

    def close(self) -> None:
        try:
            if self.state != UNPLUGGED:
                self.device.write_force(np.zeros(3))
        except (BonesimError, OSError):
            pass
        try:
            self.device.close()
        finally:
            if self.fallback is not None:
                self.fallback.close()

    def _unplug(self, t: float, why: str) -> None:
        self.sent_n[:] = 0.0
        self.gain = 0.0
        if self.state != UNPLUGGED:
            try:                                   # zero at once, if it still listens
                self.device.write_force(self.sent_n)
            except Exception:                      # noqa: BLE001 - it is going away
                pass
            try:
                self.device.close()
            except Exception:                      # noqa: BLE001
                pass
            self.unplugs += 1
            self._events.append((t, f"unplugged: {why}"[:64]))
        self.state = UNPLUGGED
        self._retry_at = t + self.limits.reconnect_s
        self._held = None

    def _fallback_reading(self, t: float) -> DeviceReading:
        if self.fallback is not None:
            return self.fallback.read(t)
        if self._held is not None:
            return self._held
        return DeviceReading(np.zeros(3), unit_axis((0.0, 0.0, -1.0)))

    def read(self, t_s: float) -> DeviceReading:
        """The backend's reading at ``t_s`` [s] if it is good, else the
        previous good one; the fallback's while unplugged."""
        self._dt_s = t_s - self._t if t_s > self._t else 0.0
        self._t = t_s
        self._dx_mm = 0.0
        if self.state == UNPLUGGED:
            if t_s < self._retry_at:
                return self._fallback_reading(t_s)
            try:
                self.device.open()
            except (BonesimError, OSError):
                self._retry_at = t_s + self.limits.reconnect_s
                return self._fallback_reading(t_s)
            self.replugs += 1
            self._events.append((t_s, "replugged"))
            self._last_ts = -math.inf
            self._restart(t_s)
        try:
            r = self.device.read(t_s)
        except (DeviceDisconnected, OSError) as exc:
            self._unplug(t_s, str(exc) or type(exc).__name__)
            return self._fallback_reading(t_s)
        bad = self._check(r, t_s)
        if bad is not None:
            self.rejected[bad] += 1
            if bad == "jump" and self._jumps >= self.limits.resync_samples:
                self._jumps = 0
                self._events.append((t_s, "resync"))
                self._held = None
                self.rejected[bad] -= 1            # taken after all
            else:
                return self._held if self._held is not None else self._fallback_reading(t_s)
        if self._held is None:
            self._restart(t_s)
            self._anchor[:] = r.pos_mm
        else:
            p, q = r.pos_mm, self._held.pos_mm
            self._dx_mm = math.sqrt((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2
                                    + (p[2] - q[2]) ** 2)
        self._held = r
        if r.t_s is not None:
            self._last_ts = r.t_s
        if self.state == WAITING:
            a, p = self._anchor, r.pos_mm
            if (p[0] - a[0]) ** 2 + (p[1] - a[1]) ** 2 + (p[2] - a[2]) ** 2 \
                    > self.limits.still_radius_mm ** 2:
                a[:] = p
                self._still_since = t_s
        return r

    def _check(self, r: DeviceReading, t_s: float) -> str | None:
        p, a = r.pos_mm, r.axis
        for i in range(3):
            if not (math.isfinite(p[i]) and math.isfinite(a[i])):
                self._jumps = 0
                return "nan"
        if not (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) > 0:
            return "nan"
        if r.t_s is not None and (not math.isfinite(r.t_s) or r.t_s < self._last_ts
                                  or r.t_s < t_s - self.limits.stale_s):
            return "stale"
        if self._held is not None:
            q, w = self._held.pos_mm, self.caps.workspace_mm
            if abs(p[0] - q[0]) > w[0] or abs(p[1] - q[1]) > w[1] or abs(p[2] - q[2]) > w[2]:
                self._jumps += 1
                return "jump"
        self._jumps = 0
        return None

    def write_force(self, force_n) -> None:
        """Render ``force_n`` [N] through the limits, the ramp and the clamp."""
        out = self.sent_n
        if self.state == UNPLUGGED:
            out[:] = 0.0
            return
        lim = self._limited
        fx, fy, fz = float(force_n[0]), float(force_n[1]), float(force_n[2])
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if not math.isfinite(mag):
            fx = fy = fz = mag = 0.0
        caps = self.caps
        if not self.renders:                   # nothing to limit: the force for the record
            out[0], out[1], out[2] = fx, fy, fz
            self.gain = 1.0
            self.device.write_force(out)
            return
        prev = math.sqrt(lim[0] ** 2 + lim[1] ** 2 + lim[2] ** 2)
        allowed = prev + caps.max_stiffness_n_per_mm * self._dx_mm \
            + self.limits.slew_n_per_s * self._dt_s
        allowed = min(allowed, caps.max_force_n)
        s = 1.0 if mag <= allowed else allowed / mag
        lim[0], lim[1], lim[2] = fx * s, fy * s, fz * s
        t = self._t
        if self.state == WAITING:
            if mag > self.limits.start_force_n:
                self._still_since = t
            elif t - self._still_since >= self.limits.still_for_s:
                self.state = RAMPING
                self._ramp_from = t
                self._events.append((t, "forces-on"))
        if self.state == RAMPING:
            self.gain = min(1.0, (t - self._ramp_from) / self.limits.ramp_s)
            if self.gain >= 1.0:
                self.state = ACTIVE
        elif self.state == ACTIVE:
            self.gain = 1.0
        else:
            self.gain = 0.0
        g = self.gain
        out[0], out[1], out[2] = lim[0] * g, lim[1] * g, lim[2] * g
        try:
            self.device.write_force(out)
        except (DeviceDisconnected, OSError) as exc:
            self._unplug(t, str(exc) or type(exc).__name__)
