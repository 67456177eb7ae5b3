"""The fragment finder: a background consumer that splits off cut bone.

It follows the haptic loop's tissue-event stream with its own
:class:`~bonesim.engine.replica.TissueReplica` (no surface), gathers the
removals into bursts, finds the parts they cut off
(:func:`bonesim.engine.fragments.find_parts`, the local pass) and asks the loop
to carry them out with :class:`~bonesim.runtime.commands.SplitPart` /
:class:`~bonesim.runtime.commands.ShedPart`. The haptic loop never labels
anything: it only flood-fills the one part a command names, between two steps.

The command ring has one producer in the parent. The finder therefore never
sends by itself: :meth:`FragmentFinder.poll` returns the commands of one round
for the caller to send (synchronous use: scripts, tests), and in a thread
(:meth:`FragmentFinder.start`) it queues them for the owner of the loop's
sender to send from its own thread with :meth:`FragmentFinder.pump` (the
simulator's window does, once per frame).

While commands it asked for are on their way (queued, or sent and not yet
taken by the loop), the finder keeps reading removals but does not look for
parts: its replica must show the loop's splits first, or it would find the
same part twice (harmless: a part already gone moves nothing) or choose a
keeper among parts that already left. A large part is moved by the loop in
slices over several steps (:mod:`bonesim.engine.split_jobs`); a part the
finder finds meanwhile in what is left of it is queued behind the split and
moves nothing (its voxels have gone to the new body by then).
"""
from __future__ import annotations

import queue
import threading
import time

import numpy as np

from bonesim.engine import events
from bonesim.engine.fragments import DEFAULT_MARGIN_VOXELS, DEFAULT_SPECK_VOXELS, find_parts
from bonesim.engine.replica import TissueReplica
from bonesim.runtime.commands import CommandOverflow, ShedPart, SplitPart

__all__ = ["POLL_S", "FragmentFinder", "speck_voxels_of"]

#: How often the finder's thread looks at the stream [s].
POLL_S = 0.01


def speck_voxels_of(model) -> int:
    """The case's speck size (``[fragments] speck_voxels``), or the default."""
    frag = getattr(getattr(model, "case", None), "fragments", None)
    return DEFAULT_SPECK_VOXELS if frag is None else int(frag.speck_voxels)


class FragmentFinder:
    """Finds cut-off bone behind the haptic loop (see the module docstring).

    Parameters
    ----------
    model : Model
    source : State
        The loop's state (shared memory) whose tissue ring is followed.
    status : ndarray, optional
        The loop's status record: ``epoch`` and ``commands_read`` are read.
        Without it (a state stepped in this process) the epoch is the
        replica's and commands count as taken once sent.
    speck_voxels : int, optional
        Default: the case's (:func:`speck_voxels_of`).
    margin : int
        The local pass's first margin [voxels].
    snapshot : bool
        Start from the loop's tissue now (True) or from record 0.

    Attributes
    ----------
    stats : dict
        ``rounds`` (detections run), ``boxes``, ``global`` (bodies labelled
        whole), ``split`` and ``shed`` (parts asked for), ``detect_s`` (the
        time of each round [s]).
    """

    def __init__(self, model, source, status=None, *, speck_voxels: int | None = None,
                 margin: int = DEFAULT_MARGIN_VOXELS, snapshot: bool = True):
        self.model = model
        self.status = status
        self.speck_voxels = speck_voxels_of(model) if speck_voxels is None else int(speck_voxels)
        if self.speck_voxels < 1:
            raise ValueError(f"speck_voxels must be a positive integer, got {speck_voxels!r}")
        self.margin = int(margin)
        self.replica = TissueReplica(model, source, snapshot=snapshot)
        self._ijk: list = []
        self._body: list = []
        self._wait_seq = -1                 # the last command sent
        self._queued = 0                    # rounds queued by the thread
        self._pumped = 0                    # ... and sent by pump()
        self._out: queue.Queue = queue.Queue()
        self._batch: list = []              # a round being sent by pump()
        self._thread = None
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.stats = {"rounds": 0, "boxes": 0, "global": 0, "split": 0, "shed": 0,
                      "detect_s": []}

    # ----------------------------------------------------------------- core
    def _epoch(self) -> int:
        return self.replica.epoch if self.status is None else int(self.status["epoch"])

    def _busy(self) -> bool:
        if self._queued != self._pumped:
            return True
        if self.status is None or self._wait_seq < 0:
            return False
        return int(self.status["commands_read"]) <= self._wait_seq

    def _read(self) -> None:
        rep = self.replica
        ev = rep.cursor.drain()
        # the removals of the epoch the replica ends in: a reset drops the rest
        kind = ev["kind"]
        r = np.flatnonzero(kind == events.RESET)
        if len(r):
            self._ijk.clear()
            self._body.clear()
            sl = slice(int(r[-1]) + 1, None)
        else:
            sl = slice(None)
        rem = (kind[sl] == events.REMOVED)
        if rem.any():
            self._ijk.append(ev["ijk"][sl][rem])
            self._body.append(ev["body"][sl][rem])
        rep.apply(ev, surface=False)

    def commands(self) -> list:
        """One round: read the stream; unless commands are on their way, look
        for parts in the removals gathered and return the commands for them,
        as ``(command class, params)``."""
        self._read()
        if self._busy() or not self._ijk:
            return []
        if self.status is not None and self._epoch() != self.replica.epoch:
            return []                        # the replica has not seen the reset yet
        ijk = np.concatenate(self._ijk)
        bod = np.concatenate(self._body)
        self._ijk.clear()
        self._body.clear()
        t0 = time.perf_counter()
        st = {}
        parts = find_parts(self.replica.state, ijk, bod, self.speck_voxels, self.margin, st)
        self.stats["detect_s"].append(time.perf_counter() - t0)
        self.stats["rounds"] += 1
        self.stats["boxes"] += st.get("boxes", 0)
        self.stats["global"] += st.get("global", 0)
        out = []
        epoch = self.replica.epoch
        for p in parts:
            self.stats["shed" if p.shed else "split"] += 1
            out.append((ShedPart if p.shed else SplitPart,
                        dict(body=p.body, seed=p.seed, lo=p.lo, hi=p.hi, n=p.n, epoch=epoch)))
        return out

    def poll(self, send) -> int:
        """One round in this thread, its commands sent with ``send(cls, **params)``
        (e.g. ``loop.send``); returns how many were sent."""
        cmds = self.commands()
        for cls, params in cmds:
            self._wait_seq = send(cls, **params)
        return len(cmds)

    # --------------------------------------------------------------- thread
    def start(self) -> "FragmentFinder":
        """Run the rounds in a daemon thread; send its commands with :meth:`pump`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="bonesim-fragments",
                                            daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        try:
            while not self._stop.wait(POLL_S):
                cmds = self.commands()
                if cmds:
                    self._queued += 1
                    self._out.put(cmds)
        except BaseException as exc:          # reported by pump(), never silent
            self.error = exc

    def pump(self, send) -> int:
        """Send the commands the thread queued (call from the thread that owns
        the loop's command sender); returns how many were sent. When the
        command ring is full, the rest waits for the next call.

        Raises
        ------
        RuntimeError
            The finder's thread stopped on an error (chained).
        """
        if self.error is not None:
            err, self.error = self.error, None
            raise RuntimeError(f"the fragment finder stopped: {err}") from err
        n = 0
        while True:
            if not self._batch:
                try:
                    self._batch = list(self._out.get_nowait())
                except queue.Empty:
                    return n
            while self._batch:
                cls, params = self._batch[0]
                try:
                    self._wait_seq = send(cls, **params)
                except CommandOverflow:
                    return n                # the loop is behind: the rest next time
                self._batch.pop(0)
                n += 1
            self._pumped += 1

    def close(self) -> None:
        """Stop the thread (if any)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
