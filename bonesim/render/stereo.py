"""Stereo viewing: VTK's stereo modes, eye separation in millimetres.

A surgeon looks through a binocular operating microscope; seeing the cavity
in depth is part of the skill the simulator trains. VTK renders the scene
twice, from a left and a right eye, and combines the two pictures as the
display needs (:data:`STEREO_MODES`):

==================  =========================================================
``side-by-side``    left eye in the left half, right eye in the right half
                    (3-D TVs and head-mounted displays in side-by-side mode;
                    each half is squeezed horizontally)
``anaglyph``        one picture, left eye in red, right eye in cyan (red-cyan
                    glasses; colours are desaturated to keep the channels
                    apart)
``interlaced``      alternate rows from each eye (line-polarised 3-D monitors)
``checkerboard``    alternate pixels (DLP 3-D projectors)
``quad-buffer``     OpenGL quad-buffered stereo (shutter glasses,
                    "crystal eyes"): needs a display and driver that offer a
                    stereo OpenGL context, asked for when the window is made
                    (``Scene(stereo_capable=True)``). Offscreen (EGL, OSMesa)
                    contexts and ordinary desktops have none:
                    :func:`apply_stereo` then raises :class:`StereoUnavailable`
                    instead of silently drawing mono.
==================  =========================================================

Eye separation. VTK places the two eyes by rotating the camera about the
focal point by plus and minus half its *eye angle*. Two eyes ``s`` apart on
that circle of radius ``d`` (the camera distance) subtend

    eye_angle = 2 asin(s / (2 d))      [deg]

(:func:`eye_angle_deg`), recomputed before every frame since zooming changes
``d``. The default separation (``render.toml`` ``[stereo]``) gives, at the
case cameras' distance, the convergence angle of an operating microscope.
"""
from __future__ import annotations

import math

from bonesim.errors import BonesimError

__all__ = ["STEREO_MODES", "StereoUnavailable", "eye_angle_deg", "apply_stereo"]

#: Mode name -> VTK stereo type (``vtkRenderWindow.SetStereoType`` values).
STEREO_MODES = {
    "side-by-side": 9,         # VTK_STEREO_SPLITVIEWPORT_HORIZONTAL
    "anaglyph": 7,             # VTK_STEREO_ANAGLYPH
    "interlaced": 3,           # VTK_STEREO_INTERLACED
    "checkerboard": 8,         # VTK_STEREO_CHECKERBOARD
    "quad-buffer": 1,          # VTK_STEREO_CRYSTAL_EYES
}
#: Anaglyph colour mask: left eye red (4), right eye green + blue (3).
ANAGLYPH_MASK = (4, 3)
#: Anaglyph colour saturation (0 grey .. 1 full colour): keeps the channels apart.
ANAGLYPH_SATURATION = 0.5


class StereoUnavailable(BonesimError):
    """The display offers no context for the stereo mode asked for."""


def eye_angle_deg(separation_mm: float, distance_mm: float) -> float:
    """VTK eye angle [deg] for eyes ``separation_mm`` apart at
    ``distance_mm`` from the focal point (both [mm], see the module
    docstring)."""
    s, d = float(separation_mm), float(distance_mm)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"eye separation must be finite and >= 0 mm, got {separation_mm!r}")
    if not (math.isfinite(d) and d > 0):
        raise ValueError(f"camera distance must be finite and > 0 mm, got {distance_mm!r}")
    return math.degrees(2.0 * math.asin(min(s / (2.0 * d), 1.0)))


def apply_stereo(render_window, mode: str | None, *, offscreen: bool,
                 asked_capable: bool = False) -> None:
    """Switch ``render_window`` to stereo ``mode`` (None: mono).

    Raises
    ------
    ValueError
        Unknown mode.
    StereoUnavailable
        ``quad-buffer`` on a window without a stereo OpenGL context.
    """
    if mode is None:
        render_window.StereoRenderOff()
        return
    if mode not in STEREO_MODES:
        raise ValueError(f"unknown stereo mode {mode!r}; known: {sorted(STEREO_MODES)}")
    if mode == "quad-buffer":
        if offscreen:
            raise StereoUnavailable(
                "quad-buffered stereo needs a display with a stereo OpenGL context; an "
                "offscreen window has none (use side-by-side, anaglyph, interlaced or "
                "checkerboard)", field="stereo")
        if not render_window.GetStereoCapableWindow():
            if asked_capable:          # VTK asked the display, which had none to give
                raise StereoUnavailable(
                    "the display offers no quad-buffered stereo OpenGL context (asked "
                    "for one; most desktops and virtual X servers have none)",
                    field="stereo")
            raise StereoUnavailable(
                "this window has no stereo OpenGL context: make the scene with "
                "stereo_capable=True on a display whose driver offers quad-buffered "
                "stereo (most desktops do not)", field="stereo")
    render_window.SetStereoType(STEREO_MODES[mode])
    if mode == "anaglyph":
        render_window.SetAnaglyphColorMask(*ANAGLYPH_MASK)
        render_window.SetAnaglyphColorSaturation(ANAGLYPH_SATURATION)
    render_window.StereoRenderOn()
