"""The session-size benchmark records a real, finished session."""
from __future__ import annotations

import pytest

from bonesim.bench.record import bench_session_size


def test_session_bytes_per_minute_is_a_finished_files_size():
    out = bench_session_size(quick=True)["session_bytes_per_minute"]
    assert out["run_s"] == pytest.approx(20.0, abs=0.01)
    assert out["removed_voxels"] > 1000                 # the plan drills in that time
    assert out["value"] == round(out["file_bytes"] / (out["run_s"] / 60.0))
    # samples at 1 kHz take far more than a kilobyte a minute, and a compacted
    # file far less than the raw rows (about 100 bytes a sample)
    assert 1e5 < out["value"] < 60_000 * 100
