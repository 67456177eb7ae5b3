"""The tool in the scene: burr and shaft, the suction tip, a marker sphere,
and the burr's silhouette when bone hides it.

Part of :class:`bonesim.render.scene.Scene` (a mixin, for the length of one
module). The tool geometry is built at its real size and placed by a rigid
user matrix (:func:`bonesim.render.geometry.tool_matrix`), so the lighting
stays right; sources are re-run only when a radius changes.

The hidden burr: :meth:`ToolMixin.set_tool` with ``depth_mm`` deeper than
``render.toml`` ``[hidden_burr] min_depth_mm`` also shows the burr's sphere
and the buried part of its shaft (from the burr centre back along the shaft
for ``radius + depth``) in the scene's overlay renderer, which draws over
the bone (own depth buffer, same camera), translucent in the silhouette's
colour. Units: case frame [mm].
"""
from __future__ import annotations

import numpy as np
from vtkmodules.vtkFiltersSources import vtkCylinderSource, vtkSphereSource
from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

from bonesim.render.geometry import tool_matrix, vtk_matrix

__all__ = ["ToolMixin", "BURR_IDLE_RGB", "BURR_ON_RGB", "SHAFT_RGB", "SUCTION_RGB",
           "SHAFT_LENGTH_MM", "SHAFT_MAX_RADIUS_MM", "MARKER_RGB", "MARKER_OPACITY"]

#: Steel colour of the burr when idle / when spinning, and of the shaft.
BURR_IDLE_RGB = (0.72, 0.74, 0.78)
BURR_ON_RGB = (0.95, 0.82, 0.45)
SHAFT_RGB = (0.55, 0.57, 0.6)
SUCTION_RGB = (0.35, 0.55, 0.75)
#: Shaft length drawn behind the burr [mm] and its largest radius [mm].
SHAFT_LENGTH_MM = 40.0
SHAFT_MAX_RADIUS_MM = 0.8
#: Colour (RGB 0-1) and opacity of :meth:`Scene.set_marker`'s sphere.
MARKER_RGB = (0.3, 0.85, 0.55)
MARKER_OPACITY = 0.45


class ToolMixin:
    """Tool, marker and hidden-burr silhouette of a :class:`Scene`."""

    # ------------------------------------------------------------------ tool
    def _build_tool(self):
        # geometry is built at its real size (rigid placement keeps the
        # lighting right); sources are re-run only when a radius changes
        self._burr_src = vtkSphereSource()
        self._burr_src.SetThetaResolution(40)
        self._burr_src.SetPhiResolution(28)
        self._shaft_src = vtkCylinderSource()          # along +y, from 0 to length
        self._shaft_src.SetResolution(28)
        self._shaft_src.CappingOn()
        self._burr = self._static_actor(self._burr_src, BURR_IDLE_RGB, specular=0.6)
        self._shaft = self._static_actor(self._shaft_src, SHAFT_RGB, specular=0.5)
        for a in (self._burr, self._shaft):
            a.SetVisibility(False)
            a.PickableOff()
            self.renderer.AddActor(a)
        # the hidden burr: the same sphere and the buried part of the shaft,
        # translucent, in the overlay renderer (drawn over the bone)
        hb = self.style.hidden_burr
        self._ghost_neck_src = vtkCylinderSource()
        self._ghost_neck_src.SetResolution(20)
        self._ghost_neck_src.CappingOff()
        self._ghost_burr = self._static_actor(self._burr_src, hb.rgb, specular=0.2)
        self._ghost_neck = self._static_actor(self._ghost_neck_src, hb.rgb, specular=0.2)
        for a in (self._ghost_burr, self._ghost_neck):
            p = a.GetProperty()
            p.SetOpacity(hb.opacity)
            p.SetAmbient(0.55)
            p.SetDiffuse(0.5)
            a.SetVisibility(False)
            a.PickableOff()
            self.overlay_renderer.AddActor(a)
        self.tool_depth_mm = None
        self._tool_radii = (None, None)
        self.tool_pos_mm = None
        self.tool_axis = np.array([0.0, 0.0, -1.0])
        self._marker = None                            # set_marker builds it
        self.marker_pos_mm = None
        self._suction = None                           # set_suction builds it
        self.suction_pos_mm = None

    @staticmethod
    def _static_actor(src, rgb, specular=0.3):
        m = vtkPolyDataMapper()
        m.SetInputConnection(src.GetOutputPort())
        m.ScalarVisibilityOff()
        a = vtkActor()
        a.SetMapper(m)
        p = a.GetProperty()
        p.SetColor(*rgb)
        p.SetAmbient(0.2)
        p.SetDiffuse(0.75)
        p.SetSpecular(specular)
        p.SetSpecularPower(40.0)
        return a

    def _tool_geometry(self, burr_r: float, shaft_r: float) -> None:
        if self._tool_radii == (burr_r, shaft_r):
            return
        self._burr_src.SetRadius(burr_r)
        self._shaft_src.SetRadius(shaft_r)
        self._shaft_src.SetHeight(SHAFT_LENGTH_MM)
        self._shaft_src.SetCenter(0.0, 0.5 * SHAFT_LENGTH_MM, 0.0)
        self._tool_radii = (burr_r, shaft_r)

    def set_tool(self, pos_mm, axis, radius_mm: float, drill_on: bool = False,
                 kind: str = "burr", depth_mm: float | None = None) -> None:
        """Place the tool.

        Parameters
        ----------
        pos_mm : (3,) float
            Burr centre (suction: tip centre), case frame [mm].
        axis : (3,) float
            Drill axis, from the handle toward the tip; the shaft is drawn
            along ``-axis`` from the burr centre.
        radius_mm : float
            Burr radius (suction: tube radius) [mm].
        drill_on : bool
            Drill running (the burr is drawn in a warmer colour).
        kind : {"burr", "suction"}
        depth_mm : float, optional
            Tissue between the burr and the eye [mm]
            (:func:`bonesim.physics.sightline.depth_below_surface_mm`). Deeper than
            ``render.toml`` ``[hidden_burr] min_depth_mm`` the burr is also
            drawn as a translucent silhouette over the bone, with the buried
            part of its shaft; None or shallower: not.
        """
        pos = np.asarray(pos_mm, dtype=float).reshape(3)
        ax = np.asarray(axis, dtype=float).reshape(3)
        r = float(radius_mm)
        if not (r > 0 and np.all(np.isfinite(pos)) and np.all(np.isfinite(ax))):
            raise ValueError("set_tool needs a finite position and axis and a positive radius")
        self.tool_pos_mm = pos.copy()
        n = np.linalg.norm(ax)
        self.tool_axis = ax / n if n > 0 else np.array([0.0, 0.0, -1.0])
        place = vtk_matrix(tool_matrix(pos, ax, (1.0, 1.0, 1.0)))
        if kind == "suction":
            self._tool_geometry(r, r)
            self._burr.SetVisibility(False)
            self._shaft.GetProperty().SetColor(*SUCTION_RGB)
        elif kind == "burr":
            self._tool_geometry(r, min(SHAFT_MAX_RADIUS_MM, 0.45 * r))
            self._burr.SetUserMatrix(place)
            self._burr.GetProperty().SetColor(*(BURR_ON_RGB if drill_on else BURR_IDLE_RGB))
            self._burr.SetVisibility(True)
            self._shaft.GetProperty().SetColor(*SHAFT_RGB)
        else:
            raise ValueError(f"unknown tool kind {kind!r} (burr or suction)")
        self._shaft.SetUserMatrix(place)
        self._shaft.SetVisibility(True)
        self._set_ghost(place, r, kind, depth_mm)

    def _set_ghost(self, place, r, kind, depth_mm) -> None:
        d = None if depth_mm is None else float(depth_mm)
        if d is not None and not np.isfinite(d):
            raise ValueError(f"depth_mm must be finite or None, got {depth_mm!r}")
        self.tool_depth_mm = d
        hidden = kind == "burr" and d is not None and d > self.style.hidden_burr.min_depth_mm
        if hidden:
            # the neck runs from the burr centre back along the shaft through
            # the covering tissue (the shaft outside it is seen anyway)
            length = min(SHAFT_LENGTH_MM, r + d)
            self._ghost_neck_src.SetRadius(min(SHAFT_MAX_RADIUS_MM, 0.45 * r))
            self._ghost_neck_src.SetHeight(length)
            self._ghost_neck_src.SetCenter(0.0, 0.5 * length, 0.0)
            self._ghost_burr.SetUserMatrix(place)
            self._ghost_neck.SetUserMatrix(place)
        self._ghost_burr.SetVisibility(hidden)
        self._ghost_neck.SetVisibility(hidden)

    @property
    def tool_hidden(self) -> bool:
        """Whether the hidden burr's silhouette is drawn."""
        return bool(self._ghost_burr.GetVisibility())

    def hide_tool(self) -> None:
        for a in (self._burr, self._shaft, self._ghost_burr, self._ghost_neck):
            a.SetVisibility(False)

    def set_suction(self, pos_mm, axis=None, radius_mm: float = 1.5) -> None:
        """Show a suction tip beside the burr (a tube of ``radius_mm`` [mm]
        ending at ``pos_mm`` [mm], running back along ``-axis``), or hide it
        with ``pos_mm=None``."""
        if pos_mm is None:
            if self._suction is not None:
                self._suction.SetVisibility(False)
            self.suction_pos_mm = None
            return
        pos = np.asarray(pos_mm, dtype=float).reshape(3)
        ax = np.asarray(self.tool_axis if axis is None else axis, dtype=float).reshape(3)
        r = float(radius_mm)
        if not (r > 0 and np.all(np.isfinite(pos)) and np.all(np.isfinite(ax))
                and np.linalg.norm(ax) > 0):
            raise ValueError("set_suction needs a finite tip and axis and a positive radius")
        if self._suction is None:
            self._suction_src = vtkCylinderSource()
            self._suction_src.SetResolution(24)
            self._suction_src.CappingOn()
            self._suction_src.SetHeight(SHAFT_LENGTH_MM)
            self._suction_src.SetCenter(0.0, 0.5 * SHAFT_LENGTH_MM, 0.0)
            self._suction = self._static_actor(self._suction_src, SUCTION_RGB, specular=0.4)
            self._suction.PickableOff()
            self.renderer.AddActor(self._suction)
        self._suction_src.SetRadius(r)
        self._suction.SetUserMatrix(vtk_matrix(tool_matrix(pos, ax, (1.0, 1.0, 1.0))))
        self._suction.SetVisibility(True)
        self.suction_pos_mm = pos.copy()

    def set_marker(self, pos_mm, radius_mm: float, rgb=MARKER_RGB,
                   opacity: float = MARKER_OPACITY) -> None:
        """Show a translucent sphere: a second point of interest beside the
        tool (the trainee's hand while the tool shows the instructor's).

        Parameters
        ----------
        pos_mm : (3,) float
            Centre, case frame [mm].
        radius_mm : float
            Radius [mm].
        rgb : (3,) float
            Colour, RGB in [0, 1].
        opacity : float
            In (0, 1].
        """
        pos = np.asarray(pos_mm, dtype=float).reshape(3)
        r = float(radius_mm)
        if not (r > 0 and np.all(np.isfinite(pos)) and 0 < opacity <= 1):
            raise ValueError("set_marker needs a finite centre, a positive radius and an "
                             "opacity in (0, 1]")
        if self._marker is None:
            self._marker_src = vtkSphereSource()
            self._marker_src.SetThetaResolution(24)
            self._marker_src.SetPhiResolution(16)
            self._marker = self._static_actor(self._marker_src, rgb, specular=0.2)
            self._marker.PickableOff()
            self.renderer.AddActor(self._marker)
        self._marker_src.SetRadius(r)
        self._marker.SetPosition(*pos)
        p = self._marker.GetProperty()
        p.SetColor(*rgb)
        p.SetOpacity(float(opacity))
        self._marker.SetVisibility(True)
        self.marker_pos_mm = pos.copy()
