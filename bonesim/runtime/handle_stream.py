"""An instrumented handle's angles into the recording, at a modest rate.

The ADU100 handle (:mod:`bonesim.devices.adu100`) drives the drill as a
foot pedal does, in the haptic loop's process; its calibrated angles [deg]
are what a reviewer wants to see of the hand. :class:`HandleTap` appends
them to the ``handle`` ring (:data:`bonesim.engine.events.OTHER_RINGS`)
when the handle's poller has read the box again, at most every
:data:`HANDLE_RECORD_S`, stamped with the loop's time of the step; the
recorder writes the ring as the session's ``/handle`` group
(``docs/session_schema.md``). The same tap serves the haptic loop and
in-process runs (:class:`bonesim.runtime.simulate._Recording`).
"""
from __future__ import annotations

import math

__all__ = ["HANDLE_RECORD_S", "HandleTap", "handle_of"]

#: Shortest interval between two recorded handle readings [s] (100 Hz: the
#: box answers one channel per USB round trip of a few milliseconds).
HANDLE_RECORD_S = 0.01


def handle_of(pedal):
    """The instrumented handle behind ``pedal`` (a pedal, or one wrapped in
    :class:`bonesim.devices.pedal.PedalGuard`), or None if it has no angles."""
    dev = getattr(pedal, "pedal", pedal)
    return dev if hasattr(dev, "readings_into") else None


class HandleTap:
    """Appends a handle's new readings to a ``handle`` ring (module docstring).

    Parameters
    ----------
    ring : bonesim.engine.events.Ring
        The ``handle`` ring.
    handle : ADU100Handle
        Has ``reads`` (complete polls so far) and ``readings_into(angles, counts)``.
    latest : ndarray, optional
        Also gets each recorded record's angles (the loop's
        ``status["handle_deg"]``, for the window's HUD).
    """

    def __init__(self, ring, handle, latest=None):
        self.ring = ring
        self.handle = handle
        self.latest = latest
        self._reads = -1
        self._next = -math.inf

    def __call__(self, t_s: float) -> bool:
        """Record the handle at loop time ``t_s`` [s] if it was read anew and
        the last record is :data:`HANDLE_RECORD_S` old; True if recorded."""
        h = self.handle
        if h.reads == self._reads or t_s < self._next:
            return False
        self._reads = h.reads
        self._next = t_s + HANDLE_RECORD_S
        f = self.ring.fields
        q = int(self.ring.head[0]) & (f["t_s"].shape[0] - 1)
        f["t_s"][q] = t_s
        h.readings_into(f["angles_deg"][q], f["counts"][q])
        self.ring.head[0] += 1          # publish after the record is complete
        if self.latest is not None:
            self.latest[...] = f["angles_deg"][q]
        return True
