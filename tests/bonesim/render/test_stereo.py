"""Stereo offscreen: the two eyes' pictures differ by the parallax a pinhole
camera predicts for the eye separation asked for; mono comes back exactly."""
from __future__ import annotations

import math

import numpy as np
import pytest
from vtkmodules.vtkFiltersSources import vtkSphereSource

from bonesim.render.scene import STEREO_MODES, Scene, StereoUnavailable
from bonesim.render.stereo import eye_angle_deg

W, H = 400, 200
EYE = np.array([0.0, 0.0, 100.0])          # camera 100 mm above the focal point
NEAR = np.array([0.0, 8.0, 40.0])          # a ball 40 mm in front of the focal point
VIEW_ANGLE = 30.0


@pytest.fixture
def scene(gl_info):
    sc = Scene(size=(W, H), panel=False, visible_subset=False, background=(0, 0, 0))
    sc.set_camera(EYE, (0, 0, 0), (0, 1, 0), view_angle_deg=VIEW_ANGLE)
    for c, r in (((0.0, 0.0, 0.0), 2.0), (tuple(NEAR), 1.0)):
        s = vtkSphereSource()
        s.SetCenter(*c)
        s.SetRadius(r)
        s.SetThetaResolution(32)
        s.SetPhiResolution(32)
        a = sc._static_actor(s, (1.0, 1.0, 1.0))
        a.GetProperty().SetAmbient(1.0)
        a.GetProperty().SetDiffuse(0.0)
        sc.renderer.AddActor(a)
    sc.renderer.ResetCameraClippingRange()
    yield sc
    sc.close()


def centroid_x(img, rows, channel=None, thr=100):
    v = img[rows].max(axis=2) if channel is None else img[rows][..., channel]
    ys, xs = np.nonzero(v > thr)
    assert len(xs) > 10
    return float(xs.mean())


def predicted_x(sign, sep_mm, width_px, aspect):
    """Pixel column of NEAR for the eye rotated by ``sign * angle / 2`` about
    the focal point (VTK's eyes), in a picture ``width_px`` wide whose
    projection has the aspect ``aspect``."""
    d = np.linalg.norm(EYE)
    th = sign * math.radians(eye_angle_deg(sep_mm, d)) / 2
    e = d * np.array([math.sin(th), 0.0, math.cos(th)])
    f = -e / d
    right = np.cross(f, (0.0, 1.0, 0.0))
    rel = NEAR - e
    ndc = (rel @ right) / ((rel @ f) * math.tan(math.radians(VIEW_ANGLE) / 2) * aspect)
    return (ndc + 1.0) / 2.0 * width_px - 0.5


def test_eye_angle_from_the_separation():
    assert eye_angle_deg(0.0, 50.0) == 0.0
    # eyes 2 d sin(a / 2) apart: 60 degrees for s = d
    assert eye_angle_deg(70.0, 70.0) == pytest.approx(60.0)
    assert eye_angle_deg(5.2, 65.0) == pytest.approx(math.degrees(2 * math.asin(2.6 / 65)))
    with pytest.raises(ValueError):
        eye_angle_deg(-1.0, 10.0)
    with pytest.raises(ValueError):
        eye_angle_deg(1.0, 0.0)
    assert set(STEREO_MODES) == {"side-by-side", "anaglyph", "interlaced", "checkerboard",
                                 "quad-buffer"}


def test_side_by_side_halves_differ_by_the_parallax(scene):
    mono = scene.image()
    near = slice(0, 80)                       # NEAR is drawn in the upper rows
    assert centroid_x(mono, near) == pytest.approx(W / 2 - 0.5, abs=0.6)
    sep = 10.0
    scene.set_stereo("side-by-side", sep)
    assert scene.camera.GetEyeAngle() == pytest.approx(eye_angle_deg(sep, 100.0))
    img = scene.image()
    left, right = img[:, :W // 2], img[:, W // 2:]
    # each eye's picture is squeezed into half the width (full-window aspect)
    for half, sign in ((left, -1), (right, 1)):
        assert centroid_x(half, near) == pytest.approx(predicted_x(sign, sep, W // 2, W / H),
                                                       abs=0.8)
    # the focal point has no parallax; the near ball ~12 px between the eyes
    focus = slice(90, 110)
    assert centroid_x(left, focus) == pytest.approx(centroid_x(right, focus), abs=0.3)
    parallax = centroid_x(left, near) - centroid_x(right, near)
    assert parallax > 8.0
    # twice the separation, about twice the parallax
    scene.set_stereo("side-by-side", 2 * sep)
    img = scene.image()
    p2 = centroid_x(img[:, :W // 2], near) - centroid_x(img[:, W // 2:], near)
    assert p2 == pytest.approx(2 * parallax, rel=0.1)
    # mono again: the very same picture
    scene.set_stereo(None)
    assert np.array_equal(scene.image(), mono)


def test_anaglyph_channels_and_interlaced_rows_differ(scene):
    mono = scene.image()
    near = slice(0, 80)
    sep = 10.0
    scene.set_stereo("anaglyph", sep)
    img = scene.image()
    red, cyan = centroid_x(img, near, 0, 60), centroid_x(img, near, 1, 60)
    assert red == pytest.approx(predicted_x(-1, sep, W, W / H), abs=0.8)     # left eye
    assert cyan == pytest.approx(predicted_x(1, sep, W, W / H), abs=0.8)     # right eye
    assert centroid_x(img, near, 2, 60) == pytest.approx(cyan, abs=0.3)
    scene.set_stereo("interlaced", sep)
    img = scene.image()
    even, odd = img[0::2], img[1::2]
    d = centroid_x(even, slice(0, 40)) - centroid_x(odd, slice(0, 40))
    assert abs(d) == pytest.approx(red - cyan, abs=1.5)
    scene.set_stereo(None)
    assert np.array_equal(scene.image(), mono)


def test_stereo_with_the_side_panel_and_bad_modes(gl_info):
    sc = Scene(size=(320, 160), visible_subset=False)
    sc.set_hud({"case": "x"})
    sc.set_stereo("side-by-side")
    assert sc.eye_separation_mm == pytest.approx(sc.style.stereo.eye_separation_mm)
    img = sc.image()
    assert img.shape == (160, 320, 3)
    with pytest.raises(StereoUnavailable, match="offscreen"):
        sc.set_stereo("quad-buffer")
    with pytest.raises(ValueError, match="unknown stereo mode"):
        sc.set_stereo("holographic")
    with pytest.raises(ValueError):
        sc.set_stereo("anaglyph", -3.0)
    sc.close()
