"""Video writing (bonesim.session.video): frame times of a playback, sizes, the H.264 writer."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.session.video import VideoWriter, parse_size, video_times


def test_video_times_and_sizes():
    t = video_times(10.0, 30, 1.0, 2.0, 4.0)
    assert len(t) == 60 and t[0] == 2.0 and t[1] - t[0] == pytest.approx(1 / 30)
    t = video_times(10.0, 10, 4.0)
    assert len(t) == 25 and t[-1] == pytest.approx(9.6)
    with pytest.raises(BonesimError, match="not after start"):
        video_times(0.0, 30)                     # a recording of one sample
    with pytest.raises(BonesimError, match="--end"):
        video_times(10.0, 30, start=5.0, end=4.0)
    with pytest.raises(BonesimError, match="outside the recording"):
        video_times(10.0, 30, start=11.0)
    with pytest.raises(BonesimError, match="--fps"):
        video_times(10.0, 0)
    assert parse_size("1280x720") == (1280, 720)
    with pytest.raises(BonesimError, match="must be even"):
        parse_size("641x480")
    with pytest.raises(BonesimError, match="WIDTHxHEIGHT"):
        parse_size("big")


def test_video_writer_frame_count_size_and_errors(tmp_path):
    import imageio_ffmpeg

    path = tmp_path / "ramp.mp4"
    w, h = 64, 48
    with VideoWriter(path, (w, h), fps=10) as vw:
        for k in range(12):
            img = np.zeros((h, w, 3), np.uint8)
            img[:, : 5 * k + 4] = (200, 40, 40)
            vw.write(img)
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    frames = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]
    assert meta["size"] == (w, h) and len(frames) == 12
    assert meta["codec"].startswith("h264") and meta["fps"] == pytest.approx(10)
    assert frames[5][24, 20, 0] > 150 and frames[5][24, 40, 0] < 60   # the ramp's edge
    with pytest.raises(BonesimError, match="must be even"):
        VideoWriter(tmp_path / "odd.mp4", (65, 48))
    with pytest.raises(BonesimError, match="folder does not exist"):
        VideoWriter(tmp_path / "no" / "such.mp4", (64, 48))
    with pytest.raises(BonesimError, match="is a folder"):
        VideoWriter(tmp_path, (64, 48))
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        # root may write anywhere: then /proc, which takes no new files, stands in
        target = ro / "x.mp4" if not os.access(ro, os.W_OK) else Path("/proc/x.mp4")
        with pytest.raises(BonesimError, match="cannot write the video"):
            VideoWriter(target, (64, 48))
    finally:
        ro.chmod(0o700)
    vw = VideoWriter(tmp_path / "short.mp4", (64, 48))
    with pytest.raises(ValueError, match="expected"):
        vw.write(np.zeros((10, 10, 3), np.uint8))
    vw.close()


def test_video_writer_reports_ffmpeg_failing(tmp_path):
    frame = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(BonesimError, match=r"bad.mp4: ffmpeg failed .*exit status [1-9].*"
                                           r"preset"):
        with VideoWriter(tmp_path / "bad.mp4", (64, 48), preset="no-such-preset") as vw:
            for _ in range(200):                 # until the pipe breaks, or at close
                vw.write(frame)
    assert not (tmp_path / "bad.mp4").exists()   # no broken file left behind
    with pytest.raises(KeyboardInterrupt):
        with VideoWriter(tmp_path / "cut.mp4", (64, 48)) as vw:
            vw.write(frame)
            raise KeyboardInterrupt
    assert not (tmp_path / "cut.mp4").exists()
