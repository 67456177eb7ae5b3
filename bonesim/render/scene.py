"""The rendered scene: bone surface, critical structures, tool, dust, HUD.

A :class:`Scene` owns one render window (offscreen or on an X display, see
:mod:`bonesim.render.gl`) with three renderers: the 3D view, an overlay
over it (the hidden burr) and a side panel for the HUD and the nerve
monitor (:mod:`bonesim.render.layout`). The tool lives in
:mod:`bonesim.render.tool`, the dust sprites in
:mod:`bonesim.render.dustview`; the look (material, lights, dust, panel,
stereo default) in ``bonesim/data/render.toml``. Everything here runs on the
thread that created the scene (the main thread); the only work done
elsewhere is the visible-subset computation of
:mod:`bonesim.render.meshbuf`, which touches numpy arrays only.

Units: positions in the case frame [mm], as everywhere in bonesim.

Structures
----------
:meth:`Scene.add_structures` meshes the non-bone structures once from the
initial tissue. With a bone surface in the scene, each structure is drawn
by its subset (:mod:`bonesim.render.structure_subset`): triangles sealed
inside tissue are left out until the drill opens the tissue near them
(:meth:`update_surface` passes the removed voxels on), and triangles clearly
turned away from the camera are left out whenever it moves; the meshes are
closed and opaque, drawn with back-face culling. The picture is the same,
pixel for pixel; at the native 0.19 mm voxel the phantom's structures go
from some 620,000 triangles to about 110,000 in the case camera's view.

Bodies: :meth:`Scene.update_bodies` (:mod:`bonesim.render.bodyview`) draws
every body of a :class:`~bonesim.engine.replica.TissueReplica` at its pose:
body 0 is the bone surface below, moved by its pose; fragments get actors
of their own.

Bone surface
------------
:meth:`Scene.update_surface` draws a :class:`bonesim.engine.surface.Surface` with
no per-vertex Python work: the surface's slot arrays ``pos`` (float32),
``nrm`` (float32) and ``col`` (RGBA uint8) are handed to VTK as they are
(``vtkDataArray.SetVoidArray``, no copy; re-pointed only when the surface
grows its arrays), and the live triangles are compacted by a numba pass
into an int32 buffer that a ``vtkCellArray`` uses in place. Colours are
direct scalars, normals are the surface's density-gradient normals, and
both faces are lit by those normals as they are (never turned around on
back faces: :func:`bonesim.render.bodyview.light_by_outward_normals`; the
drawn winding follows them too, :mod:`bonesim.render.meshbuf`), so a
triangle seen edge-on at a rim is never a dark speck. The material (``[bone]``) has a soft, wide
specular highlight under the microscope's headlight and fill light.

Level of detail
---------------
At native resolution (render.toml ``[lod]``: a voxel under
``max_voxel_px`` pixels, a surface of ``min_triangles`` or more) the bone
surface away from the burr is drawn with one vertex per 2x2x2 voxels
(:mod:`bonesim.render.lod`, no cracks, full detail around the burr and
wherever bone was removed: give :meth:`update_surface` the removed
voxels), one vertex per 4x4x4 voxels of smooth bone beyond ``coarse_mm``
of the burr (the second level), and
the structures are meshed on a grid twice as coarse. Checked before every
render (:meth:`_update_lod`).

Visible subset
--------------
While the camera moves the full triangle list is drawn. Once it has been
still for ``rest_s`` seconds a background thread computes the visible
subset (:mod:`bonesim.render.meshbuf`) and the scene draws that instead
until the camera moves again. Checked before every render, whoever asks for
it (the app, or the interactor while the user drags).
"""
from __future__ import annotations

import collections
import time
from pathlib import Path

import numpy as np

import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text rendering)
import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (OpenGL factories)
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import (vtkFloatArray, vtkPoints, vtkTypeInt32Array,
                                      vtkUnsignedCharArray)
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkIOImage import vtkPNGWriter
from vtkmodules.vtkRenderingCore import (vtkActor, vtkPolyDataMapper, vtkRenderer,
                                         vtkWindowToImageFilter)
from bonesim.render.bodyview import BodiesMixin, light_by_outward_normals
from bonesim.render.dustview import DustLayer
from bonesim.render.geometry import point_to, structure_polydata, tool_matrix
from bonesim.render.gl import make_render_window
from bonesim.render.layout import LayoutMixin
from bonesim.render.lod import BLOCK_SHIFT, SurfaceLOD, voxel_px
from bonesim.render.meshbuf import SurfaceBuffers
from bonesim.render.stereo import STEREO_MODES, StereoUnavailable
from bonesim.render.structures_view import StructuresMixin
from bonesim.render.style import default_style
from bonesim.render.tool import ToolMixin

__all__ = ["Scene", "tool_matrix", "structure_polydata", "STEREO_MODES", "StereoUnavailable",
           "BACKGROUND", "VIEW_ANGLE_DEG"]

#: Default background (dark, like the microscope's field edge), RGB 0-1.
BACKGROUND = (0.05, 0.06, 0.08)
#: Seconds the camera must stay still before the visible subset is built.
REST_S = 0.25
#: Camera view angle [deg]: a microscope's narrow field.
VIEW_ANGLE_DEG = 30.0


#: vtkOpenGLVertexBufferObject's coordinate shift-and-scale methods.
_NO_SHIFT_SCALE, _AUTO_SHIFT_SCALE = 0, 1


def _follow(want, cur, slack: int):
    """A block range that covers ``want`` (inclusive block ranges): ``cur``
    while it does (the lists are not made again), else ``want`` grown by
    ``slack`` blocks each way."""
    if cur is not None and np.all(cur[0] <= want[0]) and np.all(cur[1] >= want[1]):
        return cur
    return want[0] - slack, want[1] + slack


def _void_array(cls, ncomp: int, name: str | None = None):
    arr = cls()
    arr.SetNumberOfComponents(ncomp)
    if name:
        arr.SetName(name)
    return arr


class Scene(LayoutMixin, ToolMixin, BodiesMixin, StructuresMixin):
    """Everything drawn in one view, with an incremental surface update.

    Parameters
    ----------
    size : (2,) int
        Window width, height [pixels].
    offscreen : bool
        Render offscreen (no display needed) or into an X window (for
        :class:`bonesim.render.window.Window`).
    background : (3,) float
        RGB in [0, 1].
    visible_subset : bool
        Draw the visible subset once the camera rests (SPEC); False always
        draws every triangle.
    rest_s : float
        How long the camera must be still before the subset is built [s].
    title : str
        Window title (onscreen).
    panel : bool
        Dock the HUD and the nerve-monitor trace in a side column right of
        the 3D view (``render.toml`` ``[panel]``), so that nothing covers
        the field; False draws them over the view (older layout).
    style : RenderStyle, optional
        The look (default: the shipped ``bonesim/data/render.toml``).
    stereo_capable : bool
        Ask the display for a quad-buffered stereo OpenGL context (only
        needed for :meth:`set_stereo` ``"quad-buffer"``; onscreen only).

    Attributes
    ----------
    render_window : vtkRenderWindow
    renderer : vtkRenderer
        The 3D view.
    overlay_renderer : vtkRenderer
        Drawn over the 3D view with the same camera and a cleared depth
        buffer: the hidden burr's silhouette.
    panel_renderer : vtkRenderer or None
        The side column (2-D text and the monitor trace).
    gl : bonesim.render.gl.GLInfo
        The OpenGL path in use.
    surface : Surface or None
        The surface last given to :meth:`update_surface`.
    style : RenderStyle
    """

    def __init__(self, size=(800, 600), *, offscreen: bool = True,
                 background=BACKGROUND, visible_subset: bool = True,
                 rest_s: float = REST_S, title: str = "bonesim", panel: bool = True,
                 style=None, stereo_capable: bool = False):
        self.style = default_style() if style is None else style
        self.render_window, self.gl = make_render_window(offscreen, size)
        rw = self.render_window
        rw.SetWindowName(title)
        self.stereo_capable = bool(stereo_capable and not offscreen)
        if self.stereo_capable:
            rw.StereoCapableWindowOn()
        self.offscreen = bool(offscreen)
        rw.SetNumberOfLayers(2)
        ren = vtkRenderer()
        ren.SetBackground(*background)
        ren.TwoSidedLightingOn()
        ren.SetUseDepthPeeling(0)
        # Translucent props (dust sprites, water, the landmarks picture's
        # translucent bone) are blended order-independently (VTK's default)
        # except where the level of detail is on (:meth:`_update_lod`): there
        # the frame budget is tight, and order-independent blending renders
        # into extra float buffers and composites those over the whole view,
        # some 20 ms a frame in software OpenGL at 1024 x 768. Blended in draw
        # order instead, the picture differs by at most 3/255 on the drilled
        # phantom's settled dust (faint sprites), by about 3/255 on average
        # and up to some 30/255 in thick heaps of mixed wet and dry sprites
        # (tests/bonesim/render/test_scene.py).
        ren.SetUseOIT(True)
        self.renderer = ren
        rw.AddRenderer(ren)
        ov = vtkRenderer()
        ov.SetLayer(1)
        ov.SetActiveCamera(ren.GetActiveCamera())
        ov.InteractiveOff()
        ov.TwoSidedLightingOn()
        self.overlay_renderer = ov
        rw.AddRenderer(ov)
        self.panel_renderer = None
        if panel:
            pr = vtkRenderer()
            pr.SetBackground(*self.style.panel.rgb)
            pr.InteractiveOff()
            self.panel_renderer = pr
            rw.AddRenderer(pr)
        rw.SetMultiSamples(0)
        self._layout_px = None
        self._layout_viewports()
        self._build_lights()
        self.stereo_mode = None
        self.eye_separation_mm = float(self.style.stereo.eye_separation_mm)
        self.visible_subset = bool(visible_subset)
        self.rest_s = float(rest_s)
        self.voxel_mm = 0.5
        self._case_camera = None
        self._build_surface_actor()
        self._build_bodies()
        self._structures: dict = {}
        self._sealed: dict = {}        # structure name -> its drawn subset (see add_structures)
        self._coarse_structures = False
        self._cullers = None           # VTK's cullers, while the level of detail is on
        self._seal_sig = None          # camera the subsets' facing flags are for
        self._build_tool()
        self._build_dust()
        self._build_text()
        # visible-subset state machine
        self.surface = None
        self._buffers = SurfaceBuffers(coarse_min_cos=self.style.lod.coarse_min_cos)
        self._drawn = "full"
        self._cam_sig = None
        self._cam_still_since = time.perf_counter()
        self._job = None
        self._bound = (None, None, None)
        self._cell_refs = None
        self._full_bounds = None      # surface bounds while the full list was drawn
        self.stats = {"visible_jobs": 0, "visible_job_s": 0.0, "n_full": 0, "n_vis": 0}
        # frame clock
        self._frame_times = collections.deque(maxlen=61)
        self._hud_info: dict = {}
        self._hud_drawn_at = 0.0
        rw.AddObserver("StartEvent", self._before_render)
        rw.AddObserver("EndEvent", self._after_render)
        self._w2i = None

    # ------------------------------------------------------------ factories
    @classmethod
    def from_model(cls, model, surface=None, *, structures: bool = True, **kwargs) -> "Scene":
        """A scene of a :class:`bonesim.engine.model.Model`: its surface (built from
        the model's grid when not given), its non-bone structures, the case
        camera and the burr in the HUD.

        Parameters
        ----------
        model : Model
        surface : Surface, optional
            The surface to draw (e.g. the app's surface consumer's).
        structures : bool
            Mesh and draw the non-bone structures.
        **kwargs
            Passed to :class:`Scene`.
        """
        scene = cls(**kwargs)
        if surface is None:
            from bonesim.engine.surface import Surface

            surface = Surface.build(model.grid, model.colors)
        scene.voxel_mm = float(model.spacing_mm)
        scene.update_surface(surface)
        if structures:
            scene.add_structures(model.grid, model.structures)
        cam = getattr(getattr(model, "case", None), "camera", None)
        if cam is not None:
            scene.set_case_camera(cam.eye_mm, cam.focal_mm, cam.up)
        else:
            scene.fit_camera()
        burr = model.burr
        info = {"case": model.name, "burr": getattr(burr, "name", "?")}
        if hasattr(burr, "kind"):
            info["burr_kind"] = burr.kind
        if hasattr(burr, "diameter_mm"):
            info["burr_diameter_mm"] = burr.diameter_mm
        scene.set_hud(info)
        return scene

    # ---------------------------------------------------------------- surface
    def _build_surface_actor(self):
        self._pd = vtkPolyData()
        self._pos_arr = _void_array(vtkFloatArray, 3, "pos")
        self._nrm_arr = _void_array(vtkFloatArray, 3, "Normals")
        self._col_arr = _void_array(vtkUnsignedCharArray, 4, "Colors")
        self._points = vtkPoints()
        self._points.SetData(self._pos_arr)
        self._conn_arr = vtkTypeInt32Array()
        self._offs_arr = vtkTypeInt32Array()
        self._cells = vtkCellArray()
        self._pd.SetPoints(self._points)
        self._pd.SetPolys(self._cells)
        self._pd.GetPointData().SetNormals(self._nrm_arr)
        self._pd.GetPointData().SetScalars(self._col_arr)
        m = vtkPolyDataMapper()
        m.SetInputData(self._pd)
        m.SetColorModeToDirectScalars()
        m.SetScalarModeToUsePointData()
        m.ScalarVisibilityOn()
        m.SetStatic(True)             # the pipeline never re-executes; data are pushed
        a = vtkActor()
        a.SetMapper(m)
        # free slots of the colour array have alpha 0; without this VTK would
        # scan the alphas, call the surface translucent and blend it unsorted
        a.ForceOpaqueOn()
        light_by_outward_normals(a)
        p = a.GetProperty()
        p.SetInterpolationToGouraud()
        bone = self.style.bone
        p.SetAmbient(bone.ambient)
        p.SetDiffuse(bone.diffuse)
        p.SetSpecular(bone.specular)
        p.SetSpecularPower(bone.specular_power)
        p.SetSpecularColor(*bone.specular_rgb)
        a.SetVisibility(False)
        self.renderer.AddActor(a)
        self.surface_actor = a
        self._surface_mapper = m

    def update_surface(self, surface, removed=None, touched=None) -> dict:
        """Show ``surface`` as it is now (call after each ``Surface.update``).

        Cost: one numba pass over the triangle slots plus a few VTK calls;
        vertex data are not copied. Must run on the rendering thread, and
        the surface must not be updated while a frame renders.

        Parameters
        ----------
        surface : bonesim.engine.surface.Surface
        removed, touched : (n, 3) int array_like, optional
            The voxels given to ``Surface.update`` since the previous call
            (every one of them; concatenate over several updates). They let
            the visible subset follow the changes by marks instead of a
            comparison pass over all vertices (see
            :mod:`bonesim.render.meshbuf`); leave both None if unknown.

        Returns
        -------
        dict
            ``triangles`` (live), ``drawn`` (triangles in the list drawn),
            ``mode`` (``"full"`` or ``"visible"``).
        """
        new_surface = surface is not self.surface
        if new_surface:
            self.surface = surface
            self._buffers.invalidate()
            self._cancel_job()
        if self._sealed and (new_surface or removed is not None or touched is None):
            self._update_sealed(surface, removed, new_surface)
        self._bind_vertices(surface)
        self._buffers.sync(surface, removed, touched)
        self._push_cells()
        self.surface_actor.SetVisibility(True)
        return {"triangles": self._buffers.n_full, "drawn": self._drawn_count(),
                "mode": self._drawn}

    def _bind_vertices(self, surface):
        """Point VTK's vertex arrays at the surface's (again, if it grew) and
        mark them modified."""
        bound = (surface.pos, surface.nrm, surface.col)
        if any(b is not c for b, c in zip(bound, self._bound)):
            # new or grown arrays: point VTK at them (kept alive by self._bound)
            for arr, buf in zip((self._pos_arr, self._nrm_arr, self._col_arr), bound):
                if not buf.flags.c_contiguous:
                    raise ValueError("surface arrays must be C-contiguous")
                point_to(arr, buf, buf.size)
            self._bound = bound
        else:
            self._pos_arr.Modified()
            self._nrm_arr.Modified()
            self._col_arr.Modified()
        self._points.Modified()

    def _drawn_count(self) -> int:
        b = self._buffers
        return b.n_vis if self._drawn == "visible" else b.n_full

    def _push_cells(self):
        b = self._buffers
        if b.vis_valid and self.visible_subset:
            buf, n = b.vis, b.n_vis
            self._drawn = "visible"
        else:
            buf, n = b.full, b.n_full
            self._drawn = "full"
        self._cell_refs = (buf, b.offsets)        # keep the memory VTK reads alive
        point_to(self._conn_arr, buf, 3 * n)
        point_to(self._offs_arr, b.offsets, n + 1)
        self._cells.SetData(self._offs_arr, self._conn_arr)
        self._cells.Modified()
        self._pd.Modified()
        self.stats["n_full"] = b.n_full
        self.stats["n_vis"] = b.n_vis if b.vis_valid else 0

    @property
    def drawing(self) -> str:
        """``"visible"`` when the visible subset is drawn, else ``"full"``."""
        return self._drawn

    # ----------------------------------------------------- visible subset
    def _camera_sig(self):
        c = self.renderer.GetActiveCamera()
        return (c.GetPosition(), c.GetFocalPoint(), c.GetViewUp(),
                bool(c.GetParallelProjection()))

    def _cancel_job(self):
        self._job = None          # a running thread finishes on its own; result ignored

    @staticmethod
    def _now() -> float:
        return time.perf_counter()

    def _before_render(self, *_):
        now = time.perf_counter()
        self._layout_viewports()
        sig = self._camera_sig()
        if sig != self._cam_sig:
            self._cam_sig = sig
            self._cam_still_since = now
            self._cancel_job()
            if self._buffers.vis_valid:
                self._buffers.invalidate()
                self._push_cells()
        elif (self.visible_subset and self.surface is not None and self._job is None
              and not self._buffers.vis_valid
              and now - self._cam_still_since >= self.rest_s):
            self._start_job()
        self._update_lod()
        if self._sealed and sig != self._seal_sig:
            self._face_structures(sig)
        job = self._job
        if job is not None and job.done.is_set():
            self._job = None
            if job.tag == self._cam_sig and self._buffers.adopt(job, self.surface):
                # adopt() re-read the surface: show its vertex data as of now too
                self._bind_vertices(self.surface)
                self.stats["visible_jobs"] += 1
                self.stats["visible_job_s"] = job.seconds
                self._push_cells()
        if self._hud_info and now - self._hud_drawn_at > 0.25:
            self._draw_hud(now)
        self._reset_clipping_range()
        self._update_stereo()

    def _update_lod(self):
        """Level of detail of the bone surface (:mod:`bonesim.render.lod`,
        ``render.toml`` ``[lod]``): on when a voxel at the focal distance
        covers fewer than ``max_voxel_px`` pixels of a surface of at least
        ``min_triangles`` triangles, full detail within ``near_mm`` of the
        burr. Pushes the lists again when that changed."""
        surf = self.surface
        if surf is None:
            return
        lod = self.style.lod
        cam = self.renderer.GetActiveCamera()
        par = bool(cam.GetParallelProjection())
        px = voxel_px(surf._spacing, cam.GetDistance(), cam.GetViewAngle(),
                      int(self.renderer.GetSize()[1]),
                      cam.GetParallelScale() if par else None)
        on = px < lod.max_voxel_px and surf.n_triangles >= lod.min_triangles
        box = mid = None
        if on and self.tool_pos_mm is not None:
            pos = self.tool_pos_mm
            if getattr(self, "_main_pose", None) is not None:
                r, t = self._main_pose[:3, :3], self._main_pose[:3, 3]
                pos = (np.asarray(pos) - t) @ r
            cur = self._buffers.lod
            box = _follow(SurfaceLOD.near_blocks(pos, lod.near_mm, surf._origin, surf._spacing),
                          None if cur is None else cur.near_box, 1)
            if lod.coarse_mm > 0 and px < lod.coarse_max_voxel_px:
                # the second level beyond coarse_mm of the burr
                slack = int(np.ceil(lod.coarse_slack_mm / (surf._spacing * (1 << BLOCK_SHIFT))))
                mid = _follow(SurfaceLOD.near_blocks(pos, lod.coarse_mm, surf._origin,
                                                     surf._spacing),
                              None if cur is None else cur.mid_box, slack)
        self.renderer.SetUseOIT(not on)
        self.dust.keep_one_in = int(lod.dust_keep_one_in) if on else 1
        # where the level of detail is on the surface's vertex buffers are
        # uploaded every frame while drilling: VTK's automatic shift and
        # scale of the coordinates would scan all of them for their range
        # each time (some 1.5 ms at 0.19 mm); positions in mm of a case
        # need neither (float32 keeps about 1e-5 mm there)
        self._surface_mapper.SetVBOShiftScaleMethod(_NO_SHIFT_SCALE if on else _AUTO_SHIFT_SCALE)
        # and VTK's frustum culler would measure the surface (a pass over
        # the points its cells use) at every frame the cells changed, some
        # 2 ms at 0.19 mm, to find whether it is in view; every prop of a
        # scene of the case is in view or clipped anyway
        cullers = self.renderer.GetCullers()
        if on and cullers.GetNumberOfItems():
            self._cullers = [cullers.GetItemAsObject(i)
                             for i in range(cullers.GetNumberOfItems())]
            cullers.RemoveAllItems()
        elif not on and self._cullers:
            for c in self._cullers:
                self.renderer.AddCuller(c)
            self._cullers = None
        if self._buffers.set_lod(surf, on, box, mid):
            self._push_cells()

    def _reset_clipping_range(self):
        """Near and far planes from the bounds of everything drawn, taking
        the bone surface's bounds from its full triangle list even while the
        visible subset is drawn: VTK measures a mesh by the points its cells
        use, so the subset alone would move the planes, and with them the
        depth resolution, and change the picture."""
        ren, sa = self.renderer, self.surface_actor
        if self._drawn != "visible" or self._full_bounds is None:
            ren.ResetCameraClippingRange()
            if sa.GetVisibility() and self._buffers.n_full:
                self._full_bounds = sa.GetBounds()
            return
        lo = np.array(self._full_bounds[0::2], dtype=float)
        hi = np.array(self._full_bounds[1::2], dtype=float)
        props = ren.GetViewProps()
        props.InitTraversal()
        for _ in range(props.GetNumberOfItems()):
            p = props.GetNextProp()
            if p is sa or not p.GetVisibility() or not p.GetUseBounds():
                continue
            b = p.GetBounds()
            if b is None or b[0] > b[1]:
                continue
            lo = np.minimum(lo, b[0::2])
            hi = np.maximum(hi, b[1::2])
        ren.ResetCameraClippingRange(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])

    def _start_job(self):
        c = self.renderer.GetActiveCamera()
        # the surface's vertices are in body 0's frame (bonesim.render.bodyview)
        eye, dirn = self._to_main_frame(c.GetPosition(), c.GetDirectionOfProjection())
        self._job = self._buffers.start_visible(
            self.surface, eye, dirn, bool(c.GetParallelProjection()), tag=self._cam_sig)

    def refresh_visible(self, timeout_s: float = 10.0) -> bool:
        """Build the visible subset for the current camera now and wait for it
        (tests, benchmarks, offscreen frames). Returns True if it is drawn."""
        if self.surface is None or not self.visible_subset:
            return False
        self._cam_sig = self._camera_sig()
        self._cam_still_since = time.perf_counter() - self.rest_s
        self._buffers.invalidate()
        self._start_job()
        job = self._job
        job.wait(timeout_s)
        self._before_render()
        return self._drawn == "visible"

    # ------------------------------------------------------------ structures
    # ------------------------------------------------------------------ dust
    def _build_dust(self):
        self.dust = DustLayer(self.renderer, self.style.dust)
        self.dust_actor = self.dust.actor

    def set_cut_plane(self, pose, width_mm: float = 0.0, height_mm: float = 0.0,
                      depth_mm: float = 0.0) -> None:
        """Outline the cut plane's next stroke (:mod:`bonesim.render.cutplaneview`):
        the rectangle at ``pose`` ``(cx, cy, cz [mm], qw, qx, qy, qz)`` and a
        tick ``depth_mm`` along its normal; None hides it."""
        if getattr(self, "cut_plane", None) is None:
            if pose is None:
                return
            from bonesim.render.cutplaneview import CutPlaneOutline

            self.cut_plane = CutPlaneOutline(self.renderer)
        self.cut_plane.set(pose, width_mm, height_mm, depth_mm)

    def set_water(self, positions, density, cell_mm: float | None = None, *_) -> None:
        """Show the irrigation water's top layer (pool surfaces) as a pale
        translucent sheet (:mod:`bonesim.render.waterview`);
        ``scene.set_water(*dust_water.water_sprites(dust))`` passes everything.
        ``density``: water in each cell [cells]."""
        if getattr(self, "water", None) is None:
            from bonesim.render.waterview import WaterLayer

            self.water = WaterLayer(self.renderer)
        self.water.set(positions, density,
                       float(self.voxel_mm if cell_mm is None else cell_mm))

    def set_dust(self, positions, density, cell_mm: float | None = None, age_s=None,
                 wet=None) -> None:
        """Show bone dust as soft translucent sprites (see
        :mod:`bonesim.render.dustview`); ``scene.set_dust(*dust.sprites())``
        passes everything.

        Parameters
        ----------
        positions : (n, 3) float32
            Sprite centres [mm].
        density : (n,) float32
            Dust in each sprite's cell [cells] (0 empty .. 1 full; larger
            values are clipped; empty cells are dropped).
        cell_mm : float, optional
            Dust cell edge [mm] (default: the voxel size).
        age_s : (n,) float, optional
            Age of the dust [s]: older dust fades (default: all fresh).
        wet : (n,) bool or uint8, optional
            Wet paste (darker, more translucent; default: all dry).
        """
        cell = float(self.voxel_mm if cell_mm is None else cell_mm)
        self.dust.set(positions, density, cell, age_s, wet)

    # ---------------------------------------------------------------- camera
    @property
    def camera(self):
        return self.renderer.GetActiveCamera()

    def set_camera(self, eye_mm, focal_mm, up=(0.0, 0.0, 1.0),
                   view_angle_deg: float = VIEW_ANGLE_DEG) -> None:
        """Point the camera: eye and focal point [mm], up vector."""
        c = self.renderer.GetActiveCamera()
        c.SetPosition(*map(float, eye_mm))
        c.SetFocalPoint(*map(float, focal_mm))
        c.SetViewUp(*map(float, up))
        c.OrthogonalizeViewUp()
        c.SetViewAngle(float(view_angle_deg))
        self.renderer.ResetCameraClippingRange()

    def set_case_camera(self, eye_mm, focal_mm, up=(0.0, 0.0, 1.0)) -> None:
        """Set the camera and remember it for :meth:`reset_camera`."""
        self._case_camera = (tuple(eye_mm), tuple(focal_mm), tuple(up))
        self.set_camera(eye_mm, focal_mm, up)

    def reset_camera(self) -> None:
        """Back to the case camera (or a view of everything)."""
        if self._case_camera is None:
            self.fit_camera()
        else:
            self.set_camera(*self._case_camera)

    def fit_camera(self) -> None:
        """Frame all visible props."""
        self.renderer.ResetCamera()

    def camera_pose(self) -> tuple:
        """The camera now: eye [mm], focal point [mm], up vector, as (3,) arrays."""
        c = self.renderer.GetActiveCamera()
        return (np.array(c.GetPosition()), np.array(c.GetFocalPoint()),
                np.array(c.GetViewUp()))

    def view_direction(self) -> np.ndarray:
        """Unit vector from the eye toward the focal point."""
        return np.array(self.renderer.GetActiveCamera().GetDirectionOfProjection())

    def display_to_plane(self, x: float, y: float, through_mm=None) -> np.ndarray:
        """World point under display pixel ``(x, y)`` (origin bottom-left) on
        the plane through ``through_mm`` (default: the tool, else the focal
        point) perpendicular to the view direction [mm]."""
        ren = self.renderer
        cam = ren.GetActiveCamera()
        p0 = (np.asarray(through_mm, float) if through_mm is not None
              else (self.tool_pos_mm if self.tool_pos_mm is not None
                    else np.array(cam.GetFocalPoint())))
        d = np.array(cam.GetDirectionOfProjection())
        pts = []
        for z in (0.0, 1.0):
            ren.SetDisplayPoint(float(x), float(y), z)
            ren.DisplayToWorld()
            w = np.array(ren.GetWorldPoint())
            pts.append(w[:3] / w[3])
        ray = pts[1] - pts[0]
        den = float(ray @ d)
        if abs(den) < 1e-12:
            return p0.copy()
        t = float((p0 - pts[0]) @ d) / den
        return pts[0] + t * ray

    # ------------------------------------------------------------- rendering
    def _after_render(self, *_):
        self._frame_times.append(time.perf_counter())

    @property
    def frame_hz(self) -> float | None:
        """Frames per second over the last ~60 frames (None before two)."""
        ft = self._frame_times
        if len(ft) < 2 or ft[-1] <= ft[0]:
            return None
        return (len(ft) - 1) / (ft[-1] - ft[0])

    def render(self) -> None:
        """Draw one frame."""
        self.render_window.Render()

    def image(self) -> np.ndarray:
        """Render and read the frame back.

        Returns
        -------
        (height, width, 3) uint8
            RGB, first row at the top.
        """
        self.render()
        w2i = self._grabber()
        img = w2i.GetOutput()
        w, h, _ = img.GetDimensions()
        arr = numpy_support.vtk_to_numpy(img.GetPointData().GetScalars())
        return arr.reshape(h, w, -1)[::-1, :, :3].copy()

    def _grabber(self):
        if self._w2i is None:
            w2i = vtkWindowToImageFilter()
            w2i.SetInput(self.render_window)
            w2i.SetInputBufferTypeToRGB()
            w2i.ReadFrontBufferOff()
            # callers render just before: a second render per grab would
            # double the cost of every frame read back (video export)
            w2i.ShouldRerenderOff()
            self._w2i = w2i
        self._w2i.Modified()
        self._w2i.Update()
        return self._w2i

    def screenshot(self, path) -> Path:
        """Render and save the frame as PNG; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.render()
        w2i = self._grabber()
        wr = vtkPNGWriter()
        wr.SetFileName(str(path))
        wr.SetInputConnection(w2i.GetOutputPort())
        wr.Write()
        return path

    def close(self) -> None:
        """Release the window and its GL context."""
        self._job = None
        self._w2i = None
        rw = self.render_window
        if rw is not None:
            rw.Finalize()
        self.render_window = None
