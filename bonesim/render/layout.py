"""The window around the 3D view: side panel, text, lights, stereo.

Part of :class:`bonesim.render.scene.Scene` (a mixin, for the length of one
module): nothing here is used on its own.

Layout
------
The window holds three renderers:

* the **3D view** (``scene.renderer``), left;
* the **overlay** (``scene.overlay_renderer``), the same viewport and camera
  on layer 1 with its own depth buffer: what must show through the bone
  (the hidden burr);
* the **side panel** (``scene.panel_renderer``), a column at the right
  edge, ``width_fraction`` of the window's width clamped to
  ``[min_width_px, max_width_px]`` (``render.toml`` ``[panel]``; never more
  than 45 % of the window). The nerve-monitor trace docks at its top
  (:class:`bonesim.render.trace.MonitorTrace`), the HUD at its bottom,
  and under the HUD a one-line hint (``h: help``). Nothing is drawn over
  the field except the help overlay while the user asks for it.

Without a panel (``Scene(panel=False)``) the HUD and the hint sit at the
bottom-left of the 3D view, as before.

:meth:`text_rect` is the pixel rectangle (window coordinates, origin
bottom-left) where 2-D overlays live; :attr:`text_renderer` the renderer
they go into (its viewport coordinates start at ``text_rect()[:2]``).

Lights
------
An operating microscope lights along its optical axis: a headlight (a light
at the eye, pointing at the focal point) and a weaker fill light fixed to the
camera, above and beside it (``[lights]``); VTK's automatic light kit is off.

Stereo
------
:meth:`set_stereo` (see :mod:`bonesim.render.stereo`); the eye angle follows
the camera distance before every frame.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.vtkRenderingCore import vtkLight, vtkTextActor

from bonesim.render.hud import format_hud
from bonesim.render.stereo import apply_stereo, eye_angle_deg

__all__ = ["LayoutMixin", "panel_width_px", "PANEL_PAD_PX", "GLYPH_EM", "HINT_RGB"]

#: Margin of the text in the side panel [px].
PANEL_PAD_PX = 8
#: Width of a Courier glyph per pixel of font size (to fit text in the panel).
GLYPH_EM = 0.6
#: Colour of the help hint (RGB 0-1).
HINT_RGB = (1.0, 0.86, 0.45)
#: The panel never takes more than this fraction of the window's width.
MAX_PANEL_FRACTION = 0.45


def panel_width_px(width: int, panel) -> int:
    """Width of the side panel [px] in a window ``width`` pixels wide
    (``panel``: the ``[panel]`` table of the render style)."""
    w = round(panel.width_fraction * width)
    w = min(max(w, panel.min_width_px), panel.max_width_px)
    return int(max(0, min(w, MAX_PANEL_FRACTION * width)))


def _text_actor(rgb, size=14, bg_opacity=0.0):
    a = vtkTextActor()
    tp = a.GetTextProperty()
    tp.SetFontFamilyToCourier()
    tp.SetFontSize(size)
    tp.SetColor(*rgb)
    tp.SetBackgroundColor(0.0, 0.0, 0.0)
    tp.SetBackgroundOpacity(bg_opacity)
    tp.SetVerticalJustificationToBottom()
    a.PickableOff()
    return a


class LayoutMixin:
    """Viewports, text, lights and stereo of a :class:`Scene`."""

    # ---------------------------------------------------------------- layout
    def _layout_viewports(self) -> None:
        """Size the viewports for the window's size (cheap when unchanged)."""
        rw = self.render_window
        if rw is None:
            return
        w, h = (int(v) for v in rw.GetSize())
        if self._layout_px is not None and self._layout_px[:2] == (w, h):
            return
        pw = panel_width_px(w, self.style.panel) if self.panel_renderer is not None else 0
        self._layout_px = (w, h, pw)
        fx = 1.0 - pw / w if w > 0 else 1.0
        self.renderer.SetViewport(0.0, 0.0, fx, 1.0)
        self.overlay_renderer.SetViewport(0.0, 0.0, fx, 1.0)
        if self.panel_renderer is not None:
            self.panel_renderer.SetViewport(fx, 0.0, 1.0, 1.0)

    def view_rect(self) -> tuple[int, int, int, int]:
        """Pixel rectangle ``(x0, y0, x1, y1)`` of the 3D view (window
        coordinates, origin bottom-left)."""
        self._layout_viewports()
        w, h, pw = self._layout_px
        return 0, 0, w - pw, h

    def panel_rect(self) -> tuple[int, int, int, int] | None:
        """Pixel rectangle of the side panel, or None without one."""
        if self.panel_renderer is None:
            return None
        self._layout_viewports()
        w, h, pw = self._layout_px
        return w - pw, 0, w, h

    def text_rect(self) -> tuple[int, int, int, int]:
        """Where the 2-D overlays live: the panel, else the 3D view."""
        r = self.panel_rect()
        return self.view_rect() if r is None else r

    @property
    def text_renderer(self):
        """The renderer of the 2-D overlays (the panel's, else the view's)."""
        return self.renderer if self.panel_renderer is None else self.panel_renderer

    # ---------------------------------------------------------------- lights
    def _build_lights(self) -> None:
        lt = self.style.lights
        for ren in (self.renderer, self.overlay_renderer):
            ren.AutomaticLightCreationOff()
            ren.RemoveAllLights()
            head = vtkLight()
            head.SetLightTypeToHeadlight()
            head.SetColor(*lt.headlight_rgb)
            head.SetIntensity(lt.headlight_intensity)
            ren.AddLight(head)
            fill = vtkLight()
            fill.SetLightTypeToCameraLight()
            fill.SetPosition(0.0, 0.0, 1.0)
            fill.SetFocalPoint(0.0, 0.0, 0.0)
            fill.SetDirectionAngle(lt.fill_elevation_deg, lt.fill_azimuth_deg)
            fill.SetColor(*lt.fill_rgb)
            fill.SetIntensity(lt.fill_intensity)
            ren.AddLight(fill)
        self.lights = (head, fill)

    # ------------------------------------------------------------------ text
    #: Rows at the bottom of the text area kept free (e.g. for the playback
    #: timeline when there is no panel) [px].
    text_bottom_px = 0

    def _build_text(self) -> None:
        tr = self.text_renderer
        bg = 0.0 if self.panel_renderer is not None else 0.35
        self.hud_actor = _text_actor((0.95, 0.95, 0.9), bg_opacity=bg)
        self.hud_actor.SetVisibility(False)
        tr.AddViewProp(self.hud_actor)
        self.hint_actor = _text_actor(HINT_RGB, bg_opacity=bg)
        self.hint_actor.SetInput(self.style.panel.hint)
        tr.AddViewProp(self.hint_actor)
        hlp = _text_actor((1.0, 1.0, 0.85), bg_opacity=0.7)
        hlp.GetTextProperty().SetVerticalJustificationToTop()
        hlp.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
        hlp.SetPosition(0.02, 0.97)
        hlp.SetVisibility(False)
        self.help_actor = hlp
        self.renderer.AddViewProp(hlp)
        self._place_text()

    def set_hud(self, info: dict) -> None:
        """Replace the HUD's values (see :mod:`bonesim.render.hud` for keys;
        ``depth_mm`` shows the hidden burr's depth).

        Without a ``frame_hz`` entry the scene shows the rate it measures."""
        self._hud_info = dict(info)
        self._draw_hud(self._now())

    def set_hint(self, text: str) -> None:
        """The one-line hint under the HUD ("" hides it)."""
        self.hint_actor.SetInput(str(text))
        self.hint_actor.SetVisibility(bool(text))

    @property
    def hint_text(self) -> str:
        return self.hint_actor.GetInput() or ""

    def _font_px(self) -> int:
        """Text size for the window's height: 9 px at 300 rows, 18 px at 600+."""
        h = self.render_window.GetSize()[1] if self.render_window is not None else 600
        return int(np.clip(round(h / 33.0), 9, 18))

    def _fit_font(self, text: str) -> int:
        """:meth:`_font_px`, smaller if needed for ``text``'s longest line to
        fit the panel's width."""
        fs = self._font_px()
        if self.panel_renderer is None or not text:
            return fs
        x0, _, x1, _ = self.text_rect()
        longest = max(len(ln) for ln in text.splitlines()) if text else 1
        room = (x1 - x0) - 2 * PANEL_PAD_PX
        return int(max(7, min(fs, room // max(1.0, GLYPH_EM * longest))))

    def _place_text(self) -> None:
        """Hint at the bottom of the panel (or of the view), HUD above it."""
        hint = self.hint_actor
        hfs = self._fit_font(self.hint_text)
        if self.hud_text:                   # the same size as the HUD's
            hfs = min(hfs, self.hud_actor.GetTextProperty().GetFontSize())
        if hint.GetTextProperty().GetFontSize() != hfs:
            hint.GetTextProperty().SetFontSize(hfs)
        y0 = PANEL_PAD_PX + int(self.text_bottom_px)
        hint.SetPosition(PANEL_PAD_PX, y0)
        y = y0 + (hfs + 8 if hint.GetVisibility() and self.hint_text else 0)
        self.hud_actor.SetPosition(PANEL_PAD_PX, y)

    def _draw_hud(self, now) -> None:
        text = format_hud(self._hud_info, self.frame_hz)
        fs = self._fit_font(text)
        if self.hud_actor.GetTextProperty().GetFontSize() != fs:
            self.hud_actor.GetTextProperty().SetFontSize(fs)
        self.hud_actor.SetInput(text)
        self.hud_actor.SetVisibility(bool(self._hud_info))
        self._place_text()
        self._hud_drawn_at = now

    @property
    def hud_text(self) -> str:
        """The HUD text as drawn last."""
        return self.hud_actor.GetInput() or ""

    def set_help(self, text: str) -> None:
        """Text of the help overlay."""
        self.help_actor.SetInput(text)

    def show_help(self, visible: bool | None = None) -> bool:
        """Show, hide (or with None toggle) the help overlay; returns the new state."""
        v = (not self.help_actor.GetVisibility()) if visible is None else bool(visible)
        self.help_actor.GetTextProperty().SetFontSize(self._font_px())
        self.help_actor.SetVisibility(v)
        return v

    toggle_help = show_help

    # ---------------------------------------------------------------- stereo
    def set_stereo(self, mode: str | None, eye_separation_mm: float | None = None) -> None:
        """View in stereo (see :mod:`bonesim.render.stereo`), or mono with None.

        Parameters
        ----------
        mode : str or None
            A key of :data:`bonesim.render.stereo.STEREO_MODES`.
        eye_separation_mm : float, optional
            Distance between the eyes [mm] (default: ``render.toml``
            ``[stereo] eye_separation_mm``, or the value set last).

        Raises
        ------
        ValueError
            Unknown mode or bad separation.
        bonesim.render.stereo.StereoUnavailable
            Quad-buffered stereo without a stereo context.
        """
        if eye_separation_mm is not None:
            eye_angle_deg(eye_separation_mm, 1.0)               # validates
            self.eye_separation_mm = float(eye_separation_mm)
        apply_stereo(self.render_window, mode, offscreen=self.offscreen,
                     asked_capable=self.stereo_capable)
        self.stereo_mode = mode
        self._update_stereo()

    def _update_stereo(self) -> None:
        if self.stereo_mode is None:
            return
        cam = self.renderer.GetActiveCamera()
        d = cam.GetDistance()
        if d > 0:
            cam.SetEyeAngle(eye_angle_deg(self.eye_separation_mm, d))
