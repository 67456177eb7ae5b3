"""The trainee's servo: :class:`Trainee` runs the 1 kHz tick (poll the source,
read the device, compute the force, write it) and keeps the trainee's tissue
replica."""
from __future__ import annotations

import math
import time

import numpy as np

from bonesim.errors import BonesimError
from bonesim.tutoring.ideal import InstructorLog, TickLog, compare
from bonesim.tutoring.law import link_gain, tutor_force
from bonesim.net.tutor_protocol import KP_N_PER_MM, LOSS_S, RAMP_S, RECOVER_S, SERVO_HZ
from bonesim.tutoring.sources import Source, LatencyLog

__all__ = ["Trainee", "warmup"]


# ------------------------------------------------------------------- trainee
class Trainee:
    """The trainee's servo: source -> controller -> device, one tick at a time.

    Parameters
    ----------
    source : Source
    device : Device
        The trainee's device (e.g. :class:`bonesim.devices.simulated_hand.SimulatedHandDevice`).
        A device with a ``place`` method is placed at the instructor's tool
        when the first sample arrives (a simulated hand picks up the stylus).
    kp_n_per_mm : float
        Controller gain K_p [N/mm].
    max_force_n : float, optional
        Force limit [N]; default the device's ``caps.max_force_n``.

    Attributes
    ----------
    force_n : (3,) float64
        The force last written to the device [N].
    gain : float
        Link gain (1 with fresh data, 0 after a loss).
    link_lost : bool
        No valid data for :data:`LOSS_S`.
    released : bool
        :meth:`release` was called: the force ramps out whatever comes.
    """

    def __init__(self, source: Source, device, kp_n_per_mm: float = KP_N_PER_MM,
                 max_force_n: float | None = None):
        if not kp_n_per_mm >= 0:
            raise ValueError("kp_n_per_mm must be >= 0")
        self.source = source
        self.device = device
        self.kp = float(kp_n_per_mm)
        self.max_force_n = float(device.caps.max_force_n if max_force_n is None
                                 else max_force_n)
        if not math.isfinite(self.max_force_n):
            raise BonesimError(f"the trainee device {device.caps.name!r} renders no force; "
                               "tutoring needs a force-feedback device")
        self.force_n = np.zeros(3)
        self.gain = 0.0
        self.link_lost = True
        self.placed = not hasattr(device, "place")
        self._released_at = math.nan
        self.ticks = 0
        self.lost_events = 0
        self._t0 = math.nan
        self._last = math.nan
        self.err = LatencyLog()                      # tracking error [mm]
        self.fmag = LatencyLog()
        self.instr = InstructorLog()                  # for the ideal follower
        self.ticklog = TickLog()
        self.device_pos = np.zeros(3)

    @property
    def released(self) -> bool:
        return self._released_at == self._released_at

    def release(self, now_s: float) -> None:
        """Let go of the trainee's device: from ``now_s`` [s] the force ramps
        to zero over :data:`RAMP_S`, as after a link loss, while the source
        still sends (the trainee quit mid-session)."""
        if not self.released:
            self._released_at = float(now_s)

    @property
    def hud_text(self) -> str:
        """One line for the trainee's display."""
        if self.link_lost:
            return self.source.lost_text
        if self.released:
            return "RELEASED"
        st = self.source.state
        return (f"following instructor  |F| {math.sqrt(self.force_n @ self.force_n):4.2f} N"
                f"  drill {'on' if st.drill else 'off'}")

    def tick(self, now_s: float) -> np.ndarray:
        """One servo tick at trainee time ``now_s`` [s]; returns the force written."""
        if self._t0 != self._t0:
            self._t0 = now_s
            self._last = now_s
        src = self.source
        src.poll(now_s)
        st = src.state
        if not self.placed and st.valid:
            self.device.place(st.pos_mm)
            self.placed = True
        r = self.device.read(now_s - self._t0)
        last = src.last_valid_s
        age = now_s - last if last == last else math.inf
        rel = self._released_at
        gain_age = age if rel != rel else max(age, LOSS_S + now_s - rel)
        self.gain = link_gain(gain_age, self.gain, now_s - self._last)
        lost = age > LOSS_S
        if lost and not self.link_lost:
            self.lost_events += 1
        self.link_lost = lost
        m = tutor_force(st.pos_mm, r.pos_mm, st.force_n, self.kp, self.max_force_n,
                        self.gain if st.valid else 0.0, self.force_n)
        self.device.write_force(self.force_n)
        self.device_pos[:] = r.pos_mm
        scored = not lost and st.valid
        if scored:
            d = st.pos_mm - r.pos_mm
            self.err.add(math.sqrt(d @ d))
            self.instr.add(st.t_s, st.pos_mm, st.force_n, now_s)
        if self.placed:
            self.ticklog.add(now_s, r.pos_mm, scored)
        self.fmag.add(m)
        self._last = now_s
        self.ticks += 1
        return self.force_n

    def run(self, duration_s: float, rate_hz: float = SERVO_HZ, clock=time.monotonic,
            until=None, on_tick=None) -> dict:
        """Tick at ``rate_hz`` for ``duration_s`` [s] (or until ``until()`` is
        true), calling ``on_tick(self)`` after each tick."""
        period = 1.0 / rate_hz
        t_end = clock() + duration_s
        deadline = clock()
        while True:
            now = clock()
            if now >= t_end or (until is not None and until()):
                break
            self.tick(now)
            if on_tick is not None:
                on_tick(self)
            deadline += period
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest)
            elif rest < -10 * period:
                deadline = clock()
        return self.stats()

    def stats(self) -> dict:
        """JSON-ready figures: ticks, link, tracking error [mm], force [N], source's."""
        e = self.err.values()
        f = self.fmag.values()
        out = {"ticks": self.ticks, "link_lost": self.link_lost,
               "link_lost_events": self.lost_events, "kp_n_per_mm": self.kp,
               "max_force_n": self.max_force_n}
        if len(e):
            out["tracking_error_mm"] = {"p50": round(float(np.percentile(e, 50)), 4),
                                        "p99": round(float(np.percentile(e, 99)), 4),
                                        "max": round(float(e.max()), 4), "n": int(len(e))}
        if len(f):
            out["force_n"] = {"mean": round(float(f.mean()), 4),
                              "max": round(float(f.max()), 4)}
        if len(e):
            out["tracking_vs_ideal"] = self.vs_ideal()
        dev = self.device
        if hasattr(dev, "state_name"):                # behind the safety layer
            out["device"] = {"state": dev.state_name, "rejected": dict(dev.rejected),
                             "unplugs": dev.unplugs, "replugs": dev.replugs}
        out.update(self.source.stats())
        return out

    def vs_ideal(self) -> dict:
        """This session's following beside the ideal follower's
        (:func:`bonesim.tutoring.ideal.compare`): the same law, gain and
        force cap on a point mass ticking at the nominal rate with no link
        delay, no join ramp and no hand, scored at this servo's scored ticks
        (the last 65 s at most) against the same reference."""
        t, p, f, seen = self.instr.arrays(seen=True)
        tick, pos, scored = self.ticklog.arrays()
        dev = self.device
        hand = ((dev.mass_kg, dev.b, dev.k) if all(hasattr(dev, a) for a in ("mass_kg", "b", "k"))
                else None)
        ramp = RECOVER_S
        limits = getattr(dev, "limits", None)                 # behind the safety layer
        if limits is not None:
            ramp = max(ramp, float(limits.ramp_s))
        return compare(tick, pos, scored, t, p, f, seen, self.kp, self.max_force_n,
                       speed=float(getattr(self.source, "speed", 1.0)), ramp_s=ramp,
                       hand=hand)

    def follow(self, duration_s: float = math.inf, stop=None, on_tick=None) -> dict:
        """Run until the source ends, ``duration_s`` [s] passes or ``stop()``
        is true (or Ctrl+C), then let the force ramp out (:meth:`release`
        if the source still sends); returns
        :meth:`stats` with the final HUD line under ``"hud"``."""
        src = self.source
        try:
            try:
                self.run(duration_s, on_tick=on_tick,
                         until=lambda: src.ended or (stop is not None and stop()))
            except KeyboardInterrupt:
                pass
            if not src.ended:
                self.release(time.monotonic())
            self.run(LOSS_S + RAMP_S + 0.01, on_tick=on_tick)
        except KeyboardInterrupt:
            pass
        s = self.stats()
        s["hud"] = self.hud_text
        return s

    def close(self) -> None:
        self.force_n[:] = 0.0
        try:
            self.device.write_force(self.force_n)
        finally:
            self.source.close()


def warmup() -> None:
    """Compile the controller and the ideal follower (cached on disk after
    the first run)."""
    from bonesim.tutoring.ideal import IdealParams, ideal_follow

    z = np.zeros(3)
    tutor_force(z, z, z, KP_N_PER_MM, 1.0, 1.0, np.zeros(3))
    ideal_follow([0.0, 0.001], np.zeros((2, 3)), np.zeros((2, 3)),
                 params=IdealParams(0.15, 0.004, 0.0005))


# ----------------------------------------------------------------------- CLI
