"""The nerve monitor's shared rate history and spike rings.

The monitor process (:mod:`bonesim.runtime.monitor`) writes them; the window's
trace, the audio clicks, the headless main job and the monitor's network
server (:mod:`bonesim.net.monitor_link`) read them.
"""
from __future__ import annotations

from bonesim.engine import events

__all__ = ["HISTORY_S", "HISTORY_CAP", "SPIKE_CAP", "shared_rings", "read_history"]

#: Rate history kept for the trace [s] (the ring holds a little more).
HISTORY_S = 5.0
#: Capacity of the shared rate history [updates] (power of two, > HISTORY_S * the
#: monitor's update rate).
HISTORY_CAP = 2048
#: Capacity of the shared spike ring [spikes] (power of two; max_hz * nerves * history).
SPIKE_CAP = 1 << 14


def shared_rings(arrays) -> tuple:
    """``(history, spikes)`` rings over a monitor block's arrays: the rate
    history (``t_s``, ``rate`` (k), ``dist`` (k)) and the spikes (``t_s``,
    ``nerve``)."""
    hist = events.Ring({"t_s": arrays["hist.t_s"], "rate": arrays["hist.rate"],
                        "dist": arrays["hist.dist"]}, arrays["hist.head"])
    spikes = events.Ring({"t_s": arrays["spikes.t_s"], "nerve": arrays["spikes.nerve"]},
                         arrays["spikes.head"])
    return hist, spikes


def read_history(hist: events.Ring, spikes: events.Ring, now: float, k: int,
                 window_s: float = HISTORY_S) -> dict:
    """The last ``window_s`` seconds before ``now`` of a monitor's rate
    history and spikes (rings as :func:`shared_rings` makes them): ``now``,
    ``t_s`` (m,), ``rate`` (m, k), ``dist`` (m, k), ``spike_t`` (s,),
    ``spike_nerve`` (s,). Reads at most half of each ring, so a writer in
    another process may go on meanwhile."""
    out = {"now": now}
    for ring, keys in ((hist, ("t_s", "rate", "dist")), (spikes, ("t_s", "nerve"))):
        stop = ring.count
        start = max(0, stop - ring.capacity // 2)
        try:
            rec = ring.read(start, stop)
        except events.RingOverflow:                     # raced by the writer
            rec = ring.read(stop - 1, stop) if stop else ring.read(0, 0)
        keep = rec["t_s"] >= now - window_s
        for key in keys:
            v = rec[key][keep]
            if ring is spikes:
                out["spike_" + ("t" if key == "t_s" else key)] = v
            else:
                out[key] = v[:, :k] if v.ndim == 2 else v
    return out
