"""The main job's stages side by side (bonesim.apps.frames,
showcase.advance_through: the engine steps a frame while a worker moves the
dust of the one before and another draws the one before that) give the
frames and the outcome of advancing in line, pixel for pixel."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.apps.frames import FrameWorker, Worker
from bonesim.apps.showcase import Showcase, advance_through
from bonesim.io.loading import load_model
from bonesim.io.toolpath import demo_trajectory

SIZE = (200, 150)


@pytest.fixture(scope="module")
def cuts():
    """The demo plan from the drill's start: the cortex, dust and the
    suction-irrigator's first rinse, 12 s."""
    model = load_model("phantom", "cutting-5mm")
    traj = demo_trajectory(model.case, "cutting-5mm")
    t_on = traj.t_s[np.flatnonzero(traj.drill)[0]]
    return traj.at_times(traj.t_s[(traj.t_s >= t_on - 1.0) & (traj.t_s <= t_on + 12.0)])


def _frames(traj, threaded: bool) -> tuple[list, dict]:
    out = []
    with Showcase("phantom", "cutting-5mm", trajectory=traj, size=SIZE) as sh:
        times = np.linspace(sh.start_s, sh.end_s, 7)
        if not threaded:
            for t in times:
                sh.advance(t)
                out.append(sh.image())
            return out, sh.summary()
        advance_through(sh, times, out.append)
        last = sh.image()                  # the caller may draw again after wait()
        np.testing.assert_array_equal(last, out[-1])
        return out, sh.summary()


def test_threaded_frames_are_the_frames_drawn_in_line(cuts):
    inline, s_in = _frames(cuts, threaded=False)
    threaded, s_th = _frames(cuts, threaded=True)
    assert s_in == s_th and s_in["voxels_removed"] > 100 and s_in["dust_cells"] > 0
    assert len(threaded) == len(inline) == 7
    for a, b in zip(inline, threaded):
        np.testing.assert_array_equal(a, b)
    # the frames are pictures that change as the bone is drilled
    assert np.abs(inline[0].astype(int) - inline[-1].astype(int)).mean() > 0.5


class _Scene:
    """What the worker uses of a scene: ``image()`` and ``render_window``."""

    render_window = None

    def __init__(self, fail_at: int):
        self.n, self.fail_at = 0, fail_at

    def image(self):
        self.n += 1
        if self.n == self.fail_at:
            raise OSError("ffmpeg went away")
        return np.full((2, 2, 3), self.n, np.uint8)


def test_an_error_on_the_worker_reaches_the_caller_at_the_next_wait():
    got = []
    w = FrameWorker(_Scene(fail_at=2), got.append)
    assert isinstance(w, Worker)
    try:
        w.submit()
        w.wait()
        w.submit()
        with pytest.raises(OSError, match="ffmpeg went away"):
            w.wait()
        w.submit()                                  # it goes on after an error
        w.wait()
    finally:
        w.close()
    assert [int(g[0, 0, 0]) for g in got] == [1, 3]
