"""The landmarks picture (``bonesim case-info --png``) of a peer-style export
with a merged sinus-and-dura label, against a stored reference."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.io.case import load_case
from bonesim.render.imagecmp import compare_images, diff_image, read_png, write_png
from bonesim.render.landmarks_view import CONFIDENCE_RGB, landmarks_picture
from tests.bonesim.real_like import write_real_like

IMAGES = Path(__file__).parent / "images"
UPDATE = os.environ.get("BONESIM_UPDATE_IMAGES") == "1"


def share(img, rgb, tol=40):
    return float((np.abs(img.astype(int) - np.array(rgb)).max(axis=2) < tol).mean())


def test_landmarks_picture_of_a_merged_export(tmp_path, gl_info):
    case = load_case(write_real_like(tmp_path / "case"))
    img = read_png(landmarks_picture(case, tmp_path / "lm.png", size=(400, 300)))
    assert img.shape == (300, 400, 3)
    # split landmarks (sinus, tegmen) in cyan, found ones in green, labelled white
    assert share(img, CONFIDENCE_RGB["split"]) > 1e-4
    assert share(img, CONFIDENCE_RGB["found"]) > 1e-3
    ref_path = IMAGES / "landmarks_merged.png"
    if UPDATE:
        write_png(ref_path, img)
        pytest.skip(f"wrote {ref_path}")
    res = compare_images(img, read_png(ref_path))
    if not res:
        write_png(tmp_path / "diff.png", diff_image(img, read_png(ref_path)))
    assert res, f"{res.reason} (diff in {tmp_path})"


def test_case_info_png_command(tmp_path, gl_info):
    out = tmp_path / "p.png"
    r = subprocess.run([sys.executable, "-m", "bonesim.cli", "case-info", "phantom",
                        "--png", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "landmarks (confidence" in r.stdout and "antrum" in r.stdout
    assert out.is_file() and read_png(out).shape[2] == 3
