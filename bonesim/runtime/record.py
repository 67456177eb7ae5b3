"""The session recorder: the process that writes a running loop to a file.

A recording holds everything needed to review, replay and score a run
(the file format, its header and writer are :mod:`bonesim.session`:
``docs/session_schema.md``). The loop only appends records to shared-memory
rings (``samples`` and ``tissue``; the window adds ``camera`` and ``ui``).
A :class:`Recorder` runs a writer in its own process that drains the rings
every :data:`FLUSH_S` and appends the batches to the file
(:class:`bonesim.session.writer.SessionWriter`), which is open in HDF5's
single-writer/multiple-reader (SWMR) mode: readers may open it while it
grows, and a writer killed outright (SIGKILL) leaves a file that reads back
complete up to its last flush. In-process runs (``bonesim simulate``,
:func:`bonesim.runtime.simulate.run_trajectory`) feed a :class:`Drainer` directly.
"""
from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.runtime.child import ChildProcess
from bonesim.session.header import recorded_volume
from bonesim.session.writer import SessionWriter, kept_line

__all__ = ["FLUSH_S", "WRITER_NICE", "WHY_BYTES", "Drainer", "Recorder"]

#: How often the writer drains the rings and flushes the file [s].
FLUSH_S = 0.05
#: The writer asks for this much more CPU priority (nice -10; needs the right
#: to, as the haptic loop's real-time priority does): a starved writer falls
#: behind, and a crash then loses more than one flush period.
WRITER_NICE = 10
#: Size of the recorder's shared field saying why recording stopped [bytes].
WHY_BYTES = 400


class Drainer:
    """Moves new ring records into a :class:`SessionWriter`.

    Removals and injuries are written once the sample of their step has been
    (the loop publishes them just before that sample): a session ends with
    its last sample, and every removal in it belongs to a recorded step.

    Parameters
    ----------
    writer : SessionWriter
    rings : dict of str -> events.Ring
        Any of ``samples``, ``tissue``, ``camera``, ``ui``.
        Cursors start at record 0: the rings must not have wrapped yet.
    visibility : bonesim.physics.visibility.VisibilityTracker, optional
        Fills the removals' ``visible`` column (else -1, unknown).

    Attributes
    ----------
    visible, hidden : int
        Removals judged visible / hidden since the last case reset (the
        running visible fraction the window shows).
    """

    #: ring name -> file group, in drain order (samples before what follows them)
    TARGET = {"samples": "samples", "camera": "camera", "tissue": "tissue", "ui": "events",
              "handle": "handle"}
    #: rings held back until the samples of their steps are in
    HELD = ("tissue", "handle")

    def __init__(self, writer: SessionWriter, rings: dict, visibility=None):
        self.writer = writer
        self.cursors = {name: events.Cursor(rings[name], 0)
                        for name in self.TARGET if name in rings}
        self.visibility = visibility
        self.held = {name: None for name in self.HELD}
        self.last_t = -math.inf if "samples" in rings else math.inf
        self.rows = 0
        self.overflows = 0
        self.visible = self.hidden = 0

    def _count(self, kind, vis) -> None:
        """Add a batch's verdicts to the running counts (from 0 after a reset)."""
        resets = np.flatnonzero(kind == events.RESET)
        if len(resets):
            self.visible = self.hidden = 0
            vis = vis[resets[-1] + 1:]
        self.visible += int(np.count_nonzero(vis == 1))
        self.hidden += int(np.count_nonzero(vis == 0))

    def _take(self, name: str, cur) -> dict:
        try:
            return cur.drain()
        except events.RingOverflow:
            # the writer fell a whole ring behind (the machine stalled for a
            # minute): say so in the file and go on from what is left
            self.overflows += 1
            cur.pos = cur.ring.count - cur.ring.capacity + 1
            self.writer.append("events", {"t_s": [math.nan], "name": [b"overflow"],
                                          "value": [name.encode()]})
            return cur.drain()

    def drain(self) -> int:
        """Append everything new; returns the rows written."""
        recs = {name: self._take(name, cur) for name, cur in self.cursors.items()}
        s = recs.get("samples")
        if s is not None and len(s["t_s"]):
            self.last_t = float(s["t_s"][-1])
        for name in self.HELD:
            if name not in recs:
                continue
            r = recs[name]
            if self.held[name] is not None:
                r = {k: np.concatenate([self.held[name][k], v]) for k, v in r.items()}
            ready = r["t_s"] <= self.last_t
            self.held[name] = {k: v[~ready] for k, v in r.items()}
            recs[name] = {k: v[ready] for k, v in r.items()}
        if self.visibility is not None:
            if s is not None:
                self.visibility.add_samples(s)
            if "camera" in recs:
                self.visibility.add_camera(recs["camera"])
        if "tissue" in recs:
            r = recs["tissue"]
            r["visible"] = np.full(len(r["t_s"]), -1, np.int8) if self.visibility is None \
                else self.visibility.judge(r)
            self._count(np.asarray(r["kind"]), r["visible"])
        n = sum(self.writer.append(self.TARGET[name], r) for name, r in recs.items())
        self.rows += n
        return n


def _set_kept(status, kept: dict) -> None:
    status["kept_samples"] = kept["samples"]
    status["kept_removals"] = kept["removals"]
    status["kept_t0_s"] = math.nan if kept["t0_s"] is None else kept["t0_s"]
    status["kept_t_s"] = math.nan if kept["t_s"] is None else kept["t_s"]


def _fsize_hook() -> bool:
    """Test hook: ``BONESIM_TEST_WRITER_FSIZE`` [bytes] limits the size of
    files the writer process may write (``RLIMIT_FSIZE``; Python ignores
    SIGXFSZ, so a write past it fails with EFBIG, as on a full disk), and
    the writer then keeps no space back, so that the write itself fails.
    Returns True when the hook is set."""
    limit = os.environ.get("BONESIM_TEST_WRITER_FSIZE")
    if not limit:
        return False
    import resource
    import signal

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(limit), hard))
    return True


def _run_writer(child, loop_handle, path, header, flush_s, overwrite, models,
                eye_mm, model) -> None:
    """Body of the recorder's writer process (:meth:`Recorder.run`).

    A write that fails (or the space running out) stops the recording: the
    status's ``stopped`` and ``why`` say so, ``kept_*`` what the file holds,
    and the process ends; the parent (:meth:`Recorder.check`) tells the user.
    """
    from bonesim.runtime.haptic_loop import attach

    full_disk_test = _fsize_hook()
    lsh, rings = attach(loop_handle)
    status = child.status
    try:
        os.nice(-WRITER_NICE)    # ahead of the window and the tests' load; best effort
    except (OSError, AttributeError):
        pass
    rings = {"samples": rings["samples"], "tissue": rings["tissue"],
             "camera": child.rings["camera"], "ui": child.rings["ui"],
             **({"handle": rings["handle"]} if "handle" in rings else {})}
    vis = None
    if models is not None:
        from bonesim.physics.visibility import VisibilityTracker

        model, burrs = models
        vis = VisibilityTracker([model] + [model.with_burr(b) for b in burrs], eye_mm)
        vis.warm()                     # before ready, not at the first removal
    try:
        writer = SessionWriter(path, header, overwrite=overwrite,
                               volume=recorded_volume(model, header))
    except BaseException:
        rings.clear()
        lsh.close()
        raise
    if full_disk_test:
        import dataclasses

        writer.limits = dataclasses.replace(writer.limits, reserve_mb=0.0)
    drainer = Drainer(writer, rings, vis)
    status["kept_t0_s"] = status["kept_t_s"] = math.nan
    child.ready()
    try:
        # quit (or SIGTERM: the parent died, or terminate()) ends as asked, file complete
        while not child.quit and writer.failed is None:
            t0 = time.monotonic()
            drainer.drain()
            writer.flush()
            _set_kept(status, writer.kept)
            status["rows"] = drainer.rows
            status["flushes"] = writer.flushes
            status["overflows"] = drainer.overflows
            status["last_flush"] = time.time()
            status["visible"] = drainer.visible
            status["hidden"] = drainer.hidden
            time.sleep(max(0.0, flush_s - (time.monotonic() - t0)))
        if writer.failed is None:
            drainer.drain()
            status["rows"] = drainer.rows
            status["visible"] = drainer.visible
            status["hidden"] = drainer.hidden
    finally:
        writer.close()
        _set_kept(status, writer.kept)
        status["flushes"] = writer.flushes
        status["compacted"] = int(writer.failed is None and writer.compact_error is None)
        if writer.compact_error is not None:
            status["why"] = _encode_why(writer.compact_error)
        if writer.failed is not None:
            status["why"] = _encode_why(writer.failed)
            status["stopped"] = 1
        status["closed_ok"] = 1
        rings.clear()
        lsh.close()


def _encode_why(text: str) -> bytes:
    raw = text.encode("utf-8", errors="replace")[:WHY_BYTES]
    return raw.decode("utf-8", errors="ignore").encode()


class Recorder(ChildProcess):
    """Records a running :class:`~bonesim.runtime.haptic_loop.HapticLoop` to a file.

    The writer runs in its own process (:mod:`bonesim.runtime.child`). The window
    side may add the camera pose (:meth:`camera`) and UI events
    (:meth:`event`); both are stamped with the loop's clock.

    Parameters
    ----------
    loop : HapticLoop
        Started (or about to start) within the last minute: the writer reads
        its rings from record 0.
    path : path
        New session file.
    header : dict
        See :func:`bonesim.session.header.make_header`.
    flush_s : float
        Drain-and-flush period [s]; at most this much is lost to a crash.
    visibility : bool
        Judge each removal's visibility from the eye
        (:mod:`bonesim.physics.visibility`) in the writer: from the camera poses
        logged with :meth:`camera`, else from the case camera.

    Attributes
    ----------
    status : ndarray
        ``rows`` written, ``flushes``, ring ``overflows``, ``last_flush``
        (wall clock [s]); ``visible`` and ``hidden``: removals judged since
        the last case reset (:class:`Drainer`).
    """

    NAME = "bonesim-recorder"
    STATUS = (("rows", np.int64), ("flushes", np.int64), ("overflows", np.int64),
              ("last_flush", np.float64), ("visible", np.int64), ("hidden", np.int64),
              ("kept_t0_s", np.float64), ("kept_t_s", np.float64),
              ("kept_samples", np.int64), ("kept_removals", np.int64),
              ("stopped", np.uint8), ("closed_ok", np.uint8), ("compacted", np.uint8),
              ("why", f"S{WHY_BYTES}"))
    RINGS = ("camera", "ui")
    TERM_QUITS = True               # SIGTERM: drain the rings and close the file

    def __init__(self, loop, path, header: dict, flush_s: float = FLUSH_S,
                 overwrite: bool = False, visibility: bool = True):
        self.loop = loop
        self.path = Path(path)
        super().__init__()
        self._camera = self.rings["camera"]
        self._ui = self.rings["ui"]
        cam = getattr(getattr(loop.model, "case", None), "camera", None)
        judge = visibility and cam is not None
        self._args = {"loop_handle": loop.handle, "path": str(self.path), "header": header,
                      "flush_s": flush_s, "overwrite": overwrite,
                      "models": ((loop.model, [b for b in loop.burrs[1:]]) if judge
                                 else None),
                      "eye_mm": np.asarray(cam.eye_mm, float) if judge else None,
                      "model": loop.model}

    def child_args(self) -> dict:
        return self._args

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_writer(child, **kwargs)

    def _now(self) -> float:
        return float(self.loop.status["t_s"])

    def camera(self, eye_mm, focal_mm, up) -> None:
        """Log the camera pose (call once per frame)."""
        r = self._camera
        q = r.count & (r.capacity - 1)
        r.fields["t_s"][q] = self._now()
        r.fields["eye_mm"][q] = eye_mm
        r.fields["focal_mm"][q] = focal_mm
        r.fields["up"][q] = up
        r.head[0] += 1

    def event(self, name: str, value="") -> None:
        """Log a user-interface event (key, burr change, reset, ...)."""
        r = self._ui
        q = r.count & (r.capacity - 1)
        r.fields["t_s"][q] = self._now()
        r.fields["name"][q] = str(name).encode()[:16]
        r.fields["value"][q] = str(value).encode()[:64]
        r.head[0] += 1

    def stats(self) -> dict:
        """Rows written, flushes and overflows so far, and the recording's
        state: ``record_ok`` (False once it stopped early or the writer
        died), ``record_kept`` (``t0_s``, ``t_s``, ``samples``,
        ``removals``: what the file holds for sure) and ``record_error``
        (one line, or None)."""
        s = self.status
        t0, t1 = float(s["kept_t0_s"]), float(s["kept_t_s"])
        return {"rows": int(s["rows"]), "flushes": int(s["flushes"]),
                "overflows": int(s["overflows"]), "path": str(self.path),
                "record_ok": self.failure is None,
                "record_kept": {"t0_s": None if math.isnan(t0) else round(t0, 4),
                                "t_s": None if math.isnan(t1) else round(t1, 4),
                                "samples": int(s["kept_samples"]),
                                "removals": int(s["kept_removals"])},
                "record_error": self.failure}

    @property
    def failure(self) -> str | None:
        """One line once the recording has stopped early (see :meth:`check`)."""
        return getattr(self, "_failure", None)

    def check(self) -> str | None:
        """Look at the writer (cheap: call it every frame). Returns one line
        the first time the recording is found stopped (a write failed, the
        disk filled, the writer process died), else None; the line stays in
        :attr:`failure`."""
        if self.failure is not None or self._sh is None:
            return None
        s = self.status
        why = None
        if s["stopped"]:
            why = bytes(s["why"].item()).decode("utf-8", errors="replace")
        elif not self.running and not self.control["quit"] and self._proc is not None:
            code = self._proc.exitcode
            how = (f"killed by signal {-code}" if code is not None and code < 0
                   else f"exit code {code}")
            why = f"the recorder process died ({how})"
        if why is None:
            return None
        self._failure = kept_line(self.path, why, self.stats()["record_kept"])
        return self._failure

    def close(self, timeout_s: float = 30.0) -> dict:
        """Drain what is left, close the file cleanly and stop the writer;
        returns :meth:`stats` (idempotent). A writer that did not finish
        closing the file (it died, or stopped early) shows in
        ``record_ok``; a compaction that failed (the raw file is kept,
        complete) in ``compact_error``."""
        if self._sh is None:
            return self._final
        self.check()
        self.stop(timeout_s)
        if self.failure is None and not self.status["closed_ok"]:
            code = None if self._proc is None else self._proc.exitcode
            self._failure = kept_line(self.path, "the recorder process ended without closing "
                                      "the file" + (f" (exit code {code})" if code else ""),
                                      self.stats()["record_kept"])
        self.check()
        self._final = self.stats()
        if self.status["closed_ok"] and not self.status["compacted"] and self.failure is None:
            self._final["compact_error"] = bytes(self.status["why"].item()).decode(
                "utf-8", errors="replace")
        super().close()
        return self._final
