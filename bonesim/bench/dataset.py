"""Benchmark of vision datasets (:mod:`bonesim.render.dataset`).

``dataset_frames_per_s_640x480``
    Frames per second of ``bonesim dataset`` at 640 x 480 with RGB, depth
    and segmentation (one eye, software GL here), over a recording of the
    phantom's planned demo (its first seconds of drilling, recorded
    headless before timing): every frame replays the tissue, steps the
    re-simulated dust, draws the picture and the label pass, reads depth
    and ids back, labels the bone pixels from their voxels and writes the
    compressed HDF5 rows. Beside it, in the same run on the same recording,
    frame times and size, the plain playback video (``bonesim playback
    --video``: picture and HUD, H.264) and the ratio.
``dataset_vs_playback_video_fps``
    That ratio: dataset frames per second over playback-video frames per
    second (below 1: a dataset frame costs more than a video frame).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["SIZE", "bench_dataset"]

SIZE = (640, 480)


def bench_dataset(quick: bool = False) -> dict:
    """Both figures (see the module docstring)."""
    import numpy as np

    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model, warmup
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.render.dataset import make_dataset
    from bonesim.render.gl import select_backend
    from bonesim.render.playback import export_video
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.dataset_spec import DatasetOptions
    from bonesim.session.playback import Player
    from bonesim.session.reader import read_session

    warmup()
    gl = select_backend(offscreen=True)
    seconds = 3.0 if quick else 6.0
    fps = 4.0 if quick else 5.0
    traj = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(traj.drill)[0])
    dt = float(traj.t_s[1] - traj.t_s[0])
    part = traj.at_times(traj.t_s[start:start + int(round((seconds + 1.5) / dt))])
    with tempfile.TemporaryDirectory() as d:
        run = Path(d) / "run.h5"
        run_trajectory(load_model("phantom", "cutting-5mm"), part, surface=False, record=run)
        span = (1.0, 1.0 + seconds)
        video = export_video(Player(read_session(run)), Path(d) / "v.mp4", size=SIZE,
                             fps=fps, start=span[0], end=span[1], progress=False)
        opts = DatasetOptions(rgb=True, depth=True, seg=True, size=SIZE, fps=fps,
                              start=span[0], end=span[1])
        ds = make_dataset(run, Path(d) / "d.h5", opts)
        mb = (Path(d) / "d.h5").stat().st_size / 1e6
    ratio = ds["frames_per_s"] / video["frames_per_s"] if video["frames_per_s"] else 0.0
    detail = {"frames": ds["frames"], "size_px": list(SIZE),
              "playback_video_frames_per_s": video["frames_per_s"],
              "dataset_wall_s": ds["wall_s"], "video_wall_s": video["wall_s"],
              "dataset_mb": round(mb, 2), "streams": ["rgb", "depth", "class", "instance"],
              "gl": {"backend": gl.backend, "renderer": gl.renderer, "software": gl.software,
                     "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS",
                                                      "default (one per core)")}}
    return {"dataset_frames_per_s_640x480": {"value": ds["frames_per_s"], "unit": "frames/s",
                                             **detail},
            "dataset_vs_playback_video_fps": {"value": round(ratio, 3), "unit": "ratio",
                                              **detail}}
