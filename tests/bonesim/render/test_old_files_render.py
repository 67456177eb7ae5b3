"""Session files recorded by older bonesim play back offscreen through the
command line (``bonesim playback FILE --offscreen``), on the case version
their hashes find (tests/bonesim/session/test_old_files.py covers the rest)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1] / "data" / "sessions"


@pytest.mark.slow
@pytest.mark.parametrize("name, removed", [("phantom1_schema1.h5", "1,385"),
                                           ("phantom2_schema2.h5", "1,329")])
def test_an_old_file_plays_back_offscreen(gl_info, name, removed, tmp_path, capsys):
    from bonesim.cli.main import main
    from bonesim.render.imagecmp import read_png

    shot = tmp_path / "end.png"
    assert main(["playback", str(DATA / name), "--offscreen", "--frames", "2", "--size",
                 "320x240", "--start", "4", "--paused", "--screenshot", str(shot), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 2 and out["duration_s"] == pytest.approx(4.0)
    assert f"removed: {removed} voxels" in out["hud"] and "case   phantom" in out["hud"]
    img = read_png(shot)
    assert img.shape[:2] == (240, 320) and np.ptp(img[..., :3]) > 100   # a picture, drawn
