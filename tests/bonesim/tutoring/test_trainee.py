"""The trainee's servo in its own process: what it publishes for the window
(status and the tissue events its replica applied), how it ends, and its
errors. Real
processes, real time: a recorded run, and a live instructor over loopback."""
from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.tutoring.trainee import TraineeProcess
from tests.bonesim.plans import drilling_window
from tests.bonesim.fakes import wait_for
from tests.bonesim.session.test_playback import demo_file  # noqa: F401 (fixture)
from tests.bonesim.tutoring.test_tutor import _replay_changes

pytestmark = pytest.mark.slow

KEY = bytes(range(7, 39))


def test_recording_runs_to_its_end_and_publishes_every_tissue_event(demo_file):
    from bonesim.session.reader import read_session

    session = read_session(demo_file)
    with TraineeProcess(("recording", str(demo_file), 4.0, 0.0)) as proc:
        assert proc.model.name == "phantom" and proc.burrs == ["cutting-5mm"]
        assert proc.radius_mm(0) == 2.5 and proc.radius_mm(7) == 2.5
        assert proc.lost_text == "PLAYBACK ENDED" and str(demo_file) in proc.what
        assert proc.duration_of_source_s == pytest.approx(session.duration_s)
        assert wait_for(lambda: proc.done, 30.0)
        s = proc.status
        assert s["ended"] and s["lost"] and s["valid"]
        assert float(s["playback_s"]) == pytest.approx(session.duration_s)
        assert np.all(s["force_n"] == 0.0)     # ramped out
        # the tool stays where the recording's last polled sample put it
        late = session.samples["pos_mm"][-200:]
        assert np.all(late == s["instr_pos_mm"], axis=1).any()
        g, resets = _replay_changes(proc.model, proc.changes)
        occ = g.density > 0
        # the starting RESET, then the session's tissue stream
        assert resets == 1 and proc.changes.count == len(session.tissue["t_s"]) + 1
        ref = proc.model.grid.copy()
        for v in session.removals["ijk"]:
            ref.density[ref.brick_index(*v), (v[0] & 7) << 6 | (v[1] & 7) << 3 | (v[2] & 7)] = 0
        np.testing.assert_array_equal(occ, ref.density > 0)
        stats = proc.stop()
    assert stats["done"] and stats["hud"] == "PLAYBACK ENDED" and stats["ticks"] > 1000


def test_stop_ends_the_servo_with_its_force_ramped_out(demo_file):
    with TraineeProcess(("recording", str(demo_file), 1.0, 0.0)) as proc:
        assert wait_for(lambda: proc.status["ticks"] > 300, 20.0)
        assert not proc.done and proc.running
        t0 = time.monotonic()
        stats = proc.stop()
        assert time.monotonic() - t0 < 5.0 and proc.done and not proc.running
        assert np.all(proc.status["force_n"] == 0.0)
        assert proc.status["gain"] == 0.0 and not proc.status["lost"]
    assert 300 < stats["ticks"] and stats["playback_s"] < stats["duration_s"]
    assert stats["hud"] == "RELEASED" and stats["link_lost_events"] == 0


def test_bad_sources_are_reported_by_start(tmp_path):
    bad = tmp_path / "not-a-session.h5"
    bad.write_bytes(b"no hdf5 here")
    with pytest.raises(BonesimError, match="not-a-session.h5"):
        TraineeProcess(("recording", str(bad), 1.0, 0.0)).start()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]          # bound, silent: nobody answers
        t0 = time.monotonic()
        with pytest.raises(BonesimError, match="no answer from the instructor"):
            TraineeProcess(("network", "127.0.0.1", port, KEY, None, 0.5)).start()
        assert time.monotonic() - t0 < 30.0


class _SilentTrainee(TraineeProcess):
    """A trainee child that exits before it says anything (not even an error)."""

    @classmethod
    def run(cls, child, **kwargs) -> None:
        import os

        os._exit(3)


def test_a_child_that_dies_silently_is_reported_with_its_exit_code():
    with pytest.raises(BonesimError, match=r"exited during start-up \(exit code 3\)"):
        _SilentTrainee(("recording", "unused.h5", 1.0, 0.0)).start(timeout_s=30.0)


def test_live_instructor_over_loopback_window_replica_matches():
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.io.loading import load_model
    from bonesim.tutoring.server import TutorServer

    model = load_model("phantom", "cutting-5mm")
    traj = drilling_window("cutting-5mm", 3000)
    with HapticLoop(model, device=("scripted", traj)) as loop:
        server = TutorServer(loop, KEY, host="127.0.0.1", port=0).start()
        try:
            with TraineeProcess(("network", "127.0.0.1", server.port, KEY, None,
                                 20.0)) as proc:
                assert "127.0.0.1" in proc.what and proc.model.name == "phantom"
                assert wait_for(lambda: proc.status["ticks"] > 2000, 30.0)
                assert not proc.status["lost"]
                lat = float(proc.status["latency_ms"])     # its size is the load: a figure
                assert math.isfinite(lat) and lat >= 0.0, lat
                loop.stop()                    # the instructor's loop ends, then the server
                final = server.stop()          # says BYE: the trainee's servo ends
                assert wait_for(lambda: proc.done, 10.0)
                assert proc.status["ended"] and proc.status["lost"]
                g, resets = _replay_changes(proc.model, proc.changes)
                occ = g.density > 0
                stats = proc.stop()
        finally:
            server.stop()
        instructor = loop.state.grid.density > 0
    assert resets >= 1 and final["log_events"] > 0
    assert stats["have_events"] == final["log_events"]
    np.testing.assert_array_equal(occ, instructor)
    assert math.isfinite(stats["latency_ms"]["p50"])
