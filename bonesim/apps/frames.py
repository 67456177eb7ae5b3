"""Worker threads for the headless main job: the dust of one frame and the
drawing of another while the engine steps the next.

The headless main job (:mod:`bonesim.apps.showcase`) spends its time on
kinds of work that need not wait for each other: the engine's steps of a
frame's interval, the dust of the frame before (numba kernels that release
the GIL), and drawing the frame before that (software OpenGL, which VTK also
runs without the GIL) with its readback and video encoding.
:class:`Worker` runs one job at a time on a thread of its own (the dust:
:func:`bonesim.apps.showcase.advance_through`); :class:`FrameWorker` is the
one that draws, so the stages overlap on two cores.

For the drawing, the protocol keeps the pictures exactly those of drawing in
line:

1. the caller brings the scene to frame ``i`` (no drawing in progress);
2. :meth:`FrameWorker.submit` hands frame ``i`` to the worker, which renders,
   reads it back and passes the image to the sink (e.g. the video writer);
3. the caller simulates frame ``i + 1``, touching nothing the scene reads;
4. :meth:`FrameWorker.wait` returns once frame ``i`` is drawn and written
   (re-raising what failed there), and the caller goes on with step 1.

An OpenGL context is current in one thread at a time: the worker makes the
window's context current for each frame (VTK does on ``Render``) and releases
it after, and :meth:`FrameWorker.submit` releases the caller's, so the caller
may draw again (a final screenshot) after :meth:`FrameWorker.wait`.
"""
from __future__ import annotations

import threading

__all__ = ["Worker", "FrameWorker"]


class Worker:
    """One thread that runs submitted jobs one at a time, in order.

    Parameters
    ----------
    name : str
        The thread's name.
    """

    def __init__(self, name: str = "bonesim-worker"):
        self._job = None
        self._go = threading.Event()
        self._done = threading.Event()
        self._done.set()
        self._error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _after(self) -> None:
        """Run on the thread after each job (nothing here)."""

    def _run(self) -> None:
        while True:
            self._go.wait()
            self._go.clear()
            if self._stop:
                return
            try:
                self._job()
            except BaseException as exc:          # handed to the caller by wait()
                self._error = exc
            finally:
                self._job = None
                self._after()
                self._done.set()

    def submit(self, job) -> None:
        """Run ``job()`` on the thread after the job before it; returns at once
        (raises that job's error, if it failed)."""
        self.wait()
        self._job = job
        self._done.clear()
        self._go.set()

    def wait(self) -> None:
        """Block until the last submitted job has run; re-raise the error it
        failed with, if any."""
        self._done.wait()
        err, self._error = self._error, None
        if err is not None:
            raise err

    def close(self) -> None:
        """Let the job in progress finish (its error is not raised) and stop
        the thread. Closing twice is harmless."""
        self._done.wait()
        self._stop = True
        self._go.set()
        self._thread.join()


class FrameWorker(Worker):
    """A :class:`Worker` that draws submitted frames of a scene in order.

    Parameters
    ----------
    scene : bonesim.render.scene.Scene
        The scene; its ``image()`` renders and reads the frame back.
    sink : callable
        Called on the worker as ``sink(image)`` with each frame,
        (height, width, 3) uint8 (e.g. a video writer's ``write``).
    """

    def __init__(self, scene, sink):
        self._scene = scene
        self._sink = sink
        super().__init__("bonesim-frames")

    def _after(self) -> None:
        rw = self._scene.render_window
        if rw is not None:
            rw.ReleaseCurrent()

    def _draw(self) -> None:
        self._sink(self._scene.image())

    def submit(self) -> None:
        """Draw the scene as it is now; returns at once. The caller must not
        change the scene until :meth:`wait` returns."""
        self.wait()
        self._after()                            # the worker's thread draws it
        super().submit(self._draw)
