"""Audible clicks for the nerve monitor's spikes.

A monitoring technician listens to the nerve: every spike is a short click,
so a resting nerve ticks now and then and an irritated one crackles. Each
click is a damped sinusoid (:func:`click_template`) a few milliseconds long,
starting at zero phase (no step, so no broadband pop); each monitored nerve
gets its own pitch so the ear can tell them apart.

Timing: spikes happen in the caller's clock (the haptic loop's time, or a
remote monitor's). :class:`ClickSynth` keeps its own sample counter; the
caller anchors the two with :meth:`ClickSynth.sync` and hands spike times to
:meth:`ClickSynth.schedule`. A click sounds ``delay_s`` after its spike (the
delay absorbs the monitor's and the audio control loop's periods, so clicks
keep their spacing instead of bunching per update); a spike that arrives too
late to keep that delay sounds at once and is counted in :attr:`late`.

Threads: :meth:`schedule` (one producer thread) and :meth:`render` /
:meth:`render_add` (the audio callback) share a single-producer ring: the
producer writes a record and then moves the head, the renderer only reads
records below the head. No lock is taken.

``MixedSynth`` sums several renderers into one output stream, so the clicks
can share the drill sound's device (:mod:`bonesim.runtime.audio`).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.sound.drill import SAMPLE_RATE

__all__ = ["CLICK_HZ", "CLICK_DECAY_S", "CLICK_S", "CLICK_GAIN", "NERVE_PITCH_STEP",
           "DELAY_S", "SYNC_TOLERANCE_S", "SYNC_HOLD_S", "SYNC_JUMP_S", "click_template", "ClickSynth", "MixedSynth"]

#: Ring frequency of the first nerve's click [Hz].
CLICK_HZ = 2200.0
#: Each further nerve's click is this many times higher.
NERVE_PITCH_STEP = 1.5
#: E-folding time of a click's decay [s].
CLICK_DECAY_S = 0.0006
#: Length of a click [s] (about seven decay times: below -60 dB at its end).
CLICK_S = 0.004
#: Peak amplitude of a click.
CLICK_GAIN = 0.5
#: A click sounds this long after its spike [s].
DELAY_S = 0.03
#: :meth:`ClickSynth.sync` re-anchors the clock only beyond this drift [s] ...
SYNC_TOLERANCE_S = 0.01
#: ... held this long [s] ...
SYNC_HOLD_S = 0.5
#: ... or at once beyond this jump [s].
SYNC_JUMP_S = 0.5
#: Scheduled clicks the ring holds (power of two).
RING = 1 << 12


def click_template(sample_rate: int, nerve: int = 0) -> np.ndarray:
    """One click of nerve ``nerve``: ``CLICK_GAIN * sin(2 pi f t) * exp(-t / CLICK_DECAY_S)``
    with ``f = CLICK_HZ * NERVE_PITCH_STEP ** nerve``, ``CLICK_S`` long (float32)."""
    n = int(round(CLICK_S * sample_rate))
    t = np.arange(n) / sample_rate
    f = min(CLICK_HZ * NERVE_PITCH_STEP ** nerve, 0.4 * sample_rate)
    return (CLICK_GAIN * np.sin(2.0 * math.pi * f * t)
            * np.exp(-t / CLICK_DECAY_S)).astype(np.float32)


@njit(cache=True, nogil=True)
def click_kernel(out, s0, starts, which, head, cursor, templates, lengths):
    """Add the clicks that sound in samples ``s0 .. s0 + len(out)`` to ``out``.

    Parameters
    ----------
    out : (n,) float32
        Block to add to (clipped to [-1, 1] after).
    s0 : int
        Sample index of ``out[0]``.
    starts : (RING,) int64
        Start sample of each scheduled click (late ones are moved to ``s0``).
    which : (RING,) uint8
        Template (nerve) of each click.
    head : (1,) int64
        Clicks scheduled so far (the producer's counter).
    cursor : (3,) int64
        Renderer state: oldest click that may still sound, clicks seen, late
        clicks.
    templates : (k, L) float32
    lengths : (k,) int64
    """
    n = out.shape[0]
    mask = starts.shape[0] - 1
    h = head[0]
    for q in range(cursor[1], h):               # first sight: move late clicks to now
        j = q & mask
        if starts[j] < s0:
            starts[j] = s0
            cursor[2] += 1
    cursor[1] = h
    q = cursor[0]
    while q < h:
        j = q & mask
        st = starts[j]
        w = which[j]
        ln = lengths[w]
        if st + ln <= s0:
            if q == cursor[0]:
                cursor[0] = q + 1               # finished: let the producer reuse it
            q += 1
            continue
        if st >= s0 + n:
            break
        a = max(st, s0)
        b = min(st + ln, s0 + n)
        for s in range(a, b):
            out[s - s0] += templates[w, s - st]
        q += 1
    for s in range(n):
        out[s] = min(np.float32(1.0), max(np.float32(-1.0), out[s]))


class ClickSynth:
    """Renders scheduled clicks into audio blocks.

    Parameters
    ----------
    sample_rate : int
        [Hz]
    n_nerves : int
        Number of distinct click pitches.
    delay_s : float
        Spike-to-click delay [s].

    Attributes
    ----------
    rendered : int
        Samples rendered so far (the synth's clock).
    origin_s : float or None
        The caller's time at sample 0 (None until :meth:`sync`).
    dropped : int
        Clicks not scheduled because the ring was full.
    """

    def __init__(self, sample_rate: int = SAMPLE_RATE, n_nerves: int = 1,
                 delay_s: float = DELAY_S):
        if n_nerves < 1:
            raise ValueError(f"n_nerves must be >= 1, got {n_nerves}")
        if not delay_s >= 0:
            raise ValueError(f"delay_s must be >= 0, got {delay_s}")
        self.sample_rate = int(sample_rate)
        self.delay_s = float(delay_s)
        tmpl = [click_template(self.sample_rate, c) for c in range(n_nerves)]
        self._templates = np.zeros((n_nerves, max(len(x) for x in tmpl)), np.float32)
        for c, x in enumerate(tmpl):
            self._templates[c, :len(x)] = x
        self._lengths = np.array([len(x) for x in tmpl], dtype=np.int64)
        self._starts = np.zeros(RING, dtype=np.int64)
        self._which = np.zeros(RING, dtype=np.uint8)
        self._head = np.zeros(1, dtype=np.int64)
        self._cursor = np.zeros(3, dtype=np.int64)
        self.rendered = 0
        self.origin_s = None
        self._provisional = True
        self._off_since = None
        self.dropped = 0

    @property
    def n_nerves(self) -> int:
        return int(self._templates.shape[0])

    @property
    def scheduled(self) -> int:
        """Clicks scheduled so far."""
        return int(self._head[0])

    @property
    def late(self) -> int:
        """Clicks that sounded later than their delay (their spike came too late)."""
        return int(self._cursor[2])

    def sync(self, now_s: float, tolerance_s: float = SYNC_TOLERANCE_S,
             hold_s: float = SYNC_HOLD_S) -> bool:
        """Tie the caller's clock to the render position: the caller's clock
        reads ``now_s`` at the next sample to render. Returns True if the
        anchor moved.

        Until the first block is rendered, and once more at the first call
        after it, every call re-anchors (the output had not started). After that the anchor moves only when the clocks
        disagree by more than ``tolerance_s`` on every call for ``hold_s``
        (a real drift, e.g. a sound card's crystal against the system clock),
        or at once by more than :data:`SYNC_JUMP_S` (a new caller clock). A
        render thread that stalls and catches up, or a caller that reads its
        clock late, moves nothing: clicks keep their spacing.
        """
        origin = float(now_s) - self.rendered / self.sample_rate
        if self.origin_s is None or self._provisional or \
                abs(origin - self.origin_s) > SYNC_JUMP_S:
            moved = origin != self.origin_s
            self.origin_s = origin
            self._provisional = self.rendered == 0
            self._off_since = None
            return moved
        if abs(origin - self.origin_s) <= tolerance_s:
            self._off_since = None
            return False
        if self._off_since is None:
            self._off_since = float(now_s)
        if float(now_s) - self._off_since < hold_s:
            return False
        self.origin_s = origin
        self._off_since = None
        return True

    def schedule(self, t_s, nerve) -> int:
        """Schedule clicks for spikes at times ``t_s`` [s, the caller's clock] of
        nerves ``nerve`` (indices); returns how many were scheduled.

        Needs :meth:`sync` first. Times should not decrease between calls.
        """
        if self.origin_s is None:
            raise RuntimeError("ClickSynth.schedule before sync(): the clock is not anchored")
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        w = np.asarray(nerve, dtype=np.int64).reshape(-1)
        if len(t) != len(w):
            raise ValueError(f"{len(t)} spike times but {len(w)} nerve indices")
        if len(t) and (w.min() < 0 or w.max() >= self.n_nerves):
            raise ValueError(f"nerve index out of range 0..{self.n_nerves - 1}")
        free = RING - int(self._head[0] - self._cursor[0])
        if len(t) > free:
            self.dropped += len(t) - free
            t, w = t[:free], w[:free]
        start = np.rint((t + self.delay_s - self.origin_s) * self.sample_rate).astype(np.int64)
        h = int(self._head[0])
        idx = (h + np.arange(len(t))) & (RING - 1)
        self._starts[idx] = start
        self._which[idx] = w
        self._head[0] = h + len(t)              # publish after the records
        return len(t)

    def render_add(self, out: np.ndarray) -> np.ndarray:
        """Add the next block of clicks to ``out`` (1-D float32) and advance."""
        if out.dtype != np.float32 or out.ndim != 1:
            raise ValueError(f"out must be a 1-D float32 array, got {out.dtype} "
                             f"with shape {out.shape}")
        click_kernel(out, self.rendered, self._starts, self._which, self._head,
                     self._cursor, self._templates, self._lengths)
        self.rendered += out.shape[0]
        return out

    def render(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` with the next block of clicks alone."""
        out[:] = 0.0
        return self.render_add(out)


class MixedSynth:
    """One renderer from several: the first fills the block, the others add
    (their ``render_add``). Has the ``render`` / ``sample_rate`` interface
    :func:`bonesim.sound.drill.open_output` plays.

    Parameters
    ----------
    first : SoundSynth or ClickSynth
    *others : ClickSynth
        Same sample rate as ``first``.
    """

    def __init__(self, first, *others):
        for o in others:
            if o.sample_rate != first.sample_rate:
                raise ValueError(f"sample rates differ: {first.sample_rate} and "
                                 f"{o.sample_rate} Hz")
        self.first = first
        self.others = others
        self.sample_rate = first.sample_rate

    def render(self, out: np.ndarray) -> np.ndarray:
        self.first.render(out)
        for o in self.others:
            o.render_add(out)
        return out


def warmup() -> None:
    """Compile the click kernel (cached on disk after the first run)."""
    c = ClickSynth(SAMPLE_RATE, 1)
    c.sync(0.0)
    c.schedule([0.0], [0])
    buf = np.zeros((256, 2), dtype=np.float32)
    c.render(buf[:, 0])                               # strided (callback column)
    c.render(np.zeros(256, dtype=np.float32))
