"""Offscreen pictures of the phantom against stored references.

References live in ``images/`` (400 x 300 PNG). Regenerate them after an
intended change of the picture with::

    BONESIM_UPDATE_IMAGES=1 python -m pytest tests/bonesim/render/test_images.py

(the tests then write the images and skip). The comparison
(:func:`bonesim.render.imagecmp.compare_images`) tolerates the differences
between software rasterizers (checked here against Mesa's softpipe) but not
a burr moved by 1 mm.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bonesim.render.imagecmp import compare_images, diff_image, read_png, write_png
from tests.bonesim.render import scenes

IMAGES = Path(__file__).parent / "images"
NAMES = ("bone", "drilled", "tool", "dust")
UPDATE = os.environ.get("BONESIM_UPDATE_IMAGES") == "1"


@pytest.fixture(scope="module")
def rendered(phantom):
    """name -> (image, scene stats) for every reference picture."""
    out = {}
    for name in NAMES + ("drilled_moved", "tool_nodust", "tool_notool"):
        sc, surf, _ = scenes.build(phantom, name, visible_subset=False)
        out[name] = sc.image()
        out[name + ":scene"] = (sc.structure_names, surf.n_triangles)
        sc.close()
    return out


def check(name, img, tmp_path):
    ref_path = IMAGES / f"{name}.png"
    if UPDATE:
        write_png(ref_path, img)
        pytest.skip(f"wrote {ref_path}")
    ref = read_png(ref_path)
    res = compare_images(img, ref)
    if not res:
        write_png(tmp_path / f"{name}-actual.png", img)
        write_png(tmp_path / f"{name}-diff.png", diff_image(img, ref))
    assert res, f"{name}: {res.reason} (actual and diff images in {tmp_path})"


@pytest.mark.parametrize("name", NAMES)
def test_matches_reference(rendered, name, tmp_path):
    assert rendered[name].shape == (300, 400, 3)
    check(name, rendered[name], tmp_path)


def region_mean(img, rgb, tol=60):
    """Fraction of pixels near colour ``rgb``."""
    d = np.abs(img.astype(int) - np.array(rgb)).max(axis=2)
    return float((d < tol).mean())


def test_pictures_show_what_they_claim(rendered):
    bone, drilled, tool = rendered["bone"], rendered["drilled"], rendered["tool"]
    from bonesim.render.layout import panel_width_px
    from bonesim.render.style import default_style

    vx1 = bone.shape[1] - panel_width_px(bone.shape[1], default_style().panel)
    view = bone[:, :vx1]                                       # left of the side panel
    background = np.abs(view.astype(int) - view[0, 0]).max(axis=2) < 3
    assert 0.2 < 1.0 - background.mean() < 0.75               # the phantom, framed
    assert region_mean(view, (235, 225, 200)) > 0.15          # in its bone colour
    # drilling exposes the facial nerve (yellow) and the sigmoid sinus (blue)
    nerve, sinus = (250, 230, 40), (60, 80, 220)
    assert region_mean(drilled, nerve) > 5 * region_mean(bone, nerve) + 1e-4
    assert region_mean(drilled, sinus) > 2 * region_mean(bone, sinus)
    structures, _ = rendered["drilled:scene"]
    assert {"facial_nerve", "sigmoid_sinus", "chorda_tympani"} <= set(structures)
    assert "bone" not in structures
    # the running burr (gold) is in the close-up; dust and tool change the picture
    assert region_mean(tool, (240, 210, 115), tol=50) > 0.01
    for other in ("tool_nodust", "tool_notool"):
        res = compare_images(tool, rendered[other])
        # (light dust over the smoothly shaded, bright bone: 0.76% of pixels)
        assert not res and res.frac > 0.005, (other, res)
    # dust over the cavity: the anatomy still shows through it (the nerve and
    # the sinus keep most of their pixels), the wet paste is there (darker
    # brownish sprites), and so is the hidden burr's silhouette (cyan)
    dust = rendered["dust"]
    assert region_mean(dust, nerve) > 0.5 * region_mean(drilled, nerve)
    assert region_mean(dust, sinus) > 0.5 * region_mean(drilled, sinus)
    assert not compare_images(dust, drilled)
    assert region_mean(dust, (80, 200, 230), tol=45) > 0.002


def test_a_different_scene_fails_the_comparison(rendered):
    res = compare_images(rendered["drilled_moved"], rendered["drilled"])
    assert not res and "pixels differ" in res.reason
    res = compare_images(rendered["bone"], rendered["drilled"])
    assert not res
    assert not compare_images(rendered["bone"], rendered["bone"][:, :200])   # size


def test_visible_subset_draws_the_same_picture(phantom):
    """Same picture, same depth planes: the subset only leaves out triangles
    that cannot show."""
    sc, _, _ = scenes.build(phantom, "drilled")
    cam = sc.renderer.GetActiveCamera()
    full = sc.image()
    clip_full = cam.GetClippingRange()
    assert sc.refresh_visible() and sc.drawing == "visible"
    assert sc.stats["n_vis"] < 0.7 * sc.stats["n_full"]
    vis = sc.image()
    clip_vis = cam.GetClippingRange()
    sc.close()
    assert clip_vis == clip_full
    res = compare_images(vis, full)
    assert res and res.frac < 1e-4, res


def test_another_rasterizer_is_within_tolerance(tmp_path):
    """Mesa's softpipe (a different rasterizer from llvmpipe) stays within
    tolerance of the references."""
    if UPDATE:
        pytest.skip("updating references")
    code = ("import sys; from bonesim.io.loading import load_model; "
            "from tests.bonesim.render import scenes; "
            "from bonesim.render.imagecmp import write_png; "
            "m = load_model('phantom', 'cutting-5mm')\n"
            "for n in ('drilled', 'tool'):\n"
            "    sc, _, _ = scenes.build(m, n, visible_subset=False)\n"
            "    write_png(sys.argv[1] + '/' + n + '.png', sc.image())\n"
            "print(sc.gl.renderer)")
    env = dict(os.environ, GALLIUM_DRIVER="softpipe",
               PYTHONPATH=str(Path(__file__).resolve().parents[3]))
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    if "softpipe" not in res.stdout:
        pytest.skip(f"softpipe not available here (renderer: {res.stdout.strip()})")
    for n in ("drilled", "tool"):
        got = compare_images(read_png(tmp_path / f"{n}.png"), read_png(IMAGES / f"{n}.png"))
        assert got, f"{n}: {got.reason}"
