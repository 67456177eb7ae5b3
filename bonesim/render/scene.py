"""The rendered scene: bone surface, critical structures, tool, dust, HUD.

A :class:`Scene` owns one VTK renderer in one render window (offscreen or
on an X display, see :mod:`bonesim.render.gl`). Everything here runs on the
thread that created the scene (the main thread); the only work done
elsewhere is the visible-subset computation of
:mod:`bonesim.render.meshbuf`, which touches numpy arrays only.

Units: positions in the case frame [mm], as everywhere in bonesim.

Bone surface
------------
:meth:`Scene.update_surface` draws a :class:`bonesim.surface.Surface` with
no per-vertex Python work: the surface's slot arrays ``pos`` (float32),
``nrm`` (float32) and ``col`` (RGBA uint8) are handed to VTK as they are
(``vtkDataArray.SetVoidArray``, no copy; re-pointed only when the surface
grows its arrays), and the live triangles are compacted by a numba pass
into an int32 buffer that a ``vtkCellArray`` uses in place. Colours are
direct scalars, normals are the surface's density-gradient normals, and
both faces are lit (two-sided lighting), so the bone looks right from
inside a drilled cavity too.

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
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData
from vtkmodules.vtkCommonMath import vtkMatrix4x4
from vtkmodules.vtkFiltersCore import (vtkFlyingEdges3D, vtkPolyDataNormals,
                                       vtkWindowedSincPolyDataFilter)
from vtkmodules.vtkFiltersSources import vtkCylinderSource, vtkSphereSource
from vtkmodules.vtkIOImage import vtkPNGWriter
from vtkmodules.vtkRenderingCore import (vtkActor, vtkPointGaussianMapper, vtkPolyDataMapper,
                                         vtkRenderer, vtkTextActor, vtkWindowToImageFilter)
from .gl import make_render_window
from .hud import format_hud
from .meshbuf import SurfaceBuffers

#: Default background (dark, like the microscope's field edge), RGB 0-1.
BACKGROUND = (0.05, 0.06, 0.08)
#: Seconds the camera must stay still before the visible subset is built.
REST_S = 0.25
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
#: Bone-dust colour (RGB 0-1).
DUST_RGB = (0.93, 0.9, 0.8)
#: Camera view angle [deg]: a microscope's narrow field.
VIEW_ANGLE_DEG = 30.0

# Round soft-edged sprite for the dust splats (replaces the Gaussian's colour).
_DISK_SPLAT = (
    "//VTK::Color::Impl\n"
    "float dist2 = dot(offsetVCVSOutput.xy, offsetVCVSOutput.xy);\n"
    "if (dist2 > 1.0) { discard; }\n"
    "float fall = 1.0 - dist2 * dist2;\n"
    "ambientColor *= fall;\n"
    "diffuseColor *= fall;\n"
    "opacity *= fall;\n")


def _void_array(cls, ncomp: int, name: str | None = None):
    arr = cls()
    arr.SetNumberOfComponents(ncomp)
    if name:
        arr.SetName(name)
    return arr


def _point_to(arr, buf: np.ndarray, n_values: int) -> None:
    """Let VTK array ``arr`` use ``buf``'s memory (first ``n_values`` values)."""
    arr.SetVoidArray(buf, int(n_values), 1)   # 1: VTK must not free it
    arr.Modified()


def tool_matrix(pos_mm, axis, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """4x4 placing a model whose +y axis runs along ``-axis`` at ``pos_mm``.

    Parameters
    ----------
    pos_mm : (3,) float
        Origin of the model in the case frame [mm].
    axis : (3,) float
        Drill axis, handle toward burr tip (normalised here).
    scale : (3,) float
        Scale along the model's x, y, z before rotation.
    """
    u = -np.asarray(axis, dtype=float)
    n = np.linalg.norm(u)
    u = u / n if n > 0 else np.array([0.0, 0.0, 1.0])
    h = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(u, h)
    x /= np.linalg.norm(x)
    z = np.cross(x, u)
    m = np.eye(4)
    m[:3, 0] = x * scale[0]
    m[:3, 1] = u * scale[1]
    m[:3, 2] = z * scale[2]
    m[:3, 3] = np.asarray(pos_mm, dtype=float)
    return m


def _vtk_matrix(m: np.ndarray) -> vtkMatrix4x4:
    vm = vtkMatrix4x4()
    vm.DeepCopy(m.ravel().tolist())
    return vm


def structure_polydata(mask: np.ndarray, origin_mm, spacing_mm: float,
                       smooth_iterations: int = 15) -> vtkPolyData:
    """Smooth closed surface of a boolean voxel mask.

    Flying edges at level 0.5 on the mask padded by one empty voxel, then a
    windowed-sinc smoothing (no shrinkage) and point normals.

    Parameters
    ----------
    mask : (nx, ny, nz) bool
        Voxels of the structure, axes (x, y, z).
    origin_mm : (3,) float
        Case-frame centre of ``mask[0, 0, 0]`` [mm].
    spacing_mm : float
        Voxel edge [mm].
    smooth_iterations : int
        Smoothing passes (0: none).
    """
    pad = np.zeros(tuple(s + 2 for s in mask.shape), dtype=np.uint8)
    pad[1:-1, 1:-1, 1:-1] = mask
    img = vtkImageData()
    img.SetDimensions(*pad.shape)
    img.SetSpacing(spacing_mm, spacing_mm, spacing_mm)
    img.SetOrigin(*(np.asarray(origin_mm, dtype=float) - spacing_mm))
    flat = np.ascontiguousarray(pad.transpose(2, 1, 0)).ravel()   # x fastest
    arr = numpy_support.numpy_to_vtk(flat, deep=True)
    arr.SetName("mask")
    img.GetPointData().SetScalars(arr)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.5)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    src = fe
    if smooth_iterations > 0:
        sm = vtkWindowedSincPolyDataFilter()
        sm.SetInputConnection(fe.GetOutputPort())
        sm.SetNumberOfIterations(int(smooth_iterations))
        sm.SetPassBand(0.1)
        sm.NonManifoldSmoothingOn()
        sm.NormalizeCoordinatesOn()
        sm.BoundarySmoothingOff()
        src = sm
    nm = vtkPolyDataNormals()
    nm.SetInputConnection(src.GetOutputPort())
    nm.SplittingOff()
    nm.ConsistencyOn()
    nm.AutoOrientNormalsOff()
    nm.Update()
    out = vtkPolyData()
    out.DeepCopy(nm.GetOutput())
    return out


class Scene:
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

    Attributes
    ----------
    render_window : vtkRenderWindow
    renderer : vtkRenderer
    gl : bonesim.render.gl.GLInfo
        The OpenGL path in use.
    surface : Surface or None
        The surface last given to :meth:`update_surface`.
    """

    def __init__(self, size=(800, 600), *, offscreen: bool = True,
                 background=BACKGROUND, visible_subset: bool = True,
                 rest_s: float = REST_S, title: str = "bonesim"):
        self.render_window, self.gl = make_render_window(offscreen, size)
        self.render_window.SetWindowName(title)
        self.offscreen = bool(offscreen)
        ren = vtkRenderer()
        ren.SetBackground(*background)
        ren.TwoSidedLightingOn()
        ren.SetUseDepthPeeling(0)
        self.renderer = ren
        self.render_window.AddRenderer(ren)
        self.render_window.SetMultiSamples(0)
        self.visible_subset = bool(visible_subset)
        self.rest_s = float(rest_s)
        self.voxel_mm = 0.5
        self._case_camera = None
        self._build_surface_actor()
        self._structures: dict = {}
        self._build_tool()
        self._build_dust()
        self._build_text()
        # visible-subset state machine
        self.surface = None
        self._buffers = SurfaceBuffers()
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
        ren.AddObserver("StartEvent", self._before_render)
        ren.AddObserver("EndEvent", self._after_render)
        self._w2i = None

    # ------------------------------------------------------------ factories
    @classmethod
    def from_model(cls, model, surface=None, *, structures: bool = True, **kwargs) -> "Scene":
        """A scene of a :class:`bonesim.model.Model`: its surface (built from
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
            from ..surface import Surface

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
        p = a.GetProperty()
        p.SetInterpolationToGouraud()
        p.SetAmbient(0.12)
        p.SetDiffuse(0.85)
        p.SetSpecular(0.12)
        p.SetSpecularPower(20.0)
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
        surface : bonesim.surface.Surface
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
        if surface is not self.surface:
            self.surface = surface
            self._buffers.invalidate()
            self._cancel_job()
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
                _point_to(arr, buf, buf.size)
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
        _point_to(self._conn_arr, buf, 3 * n)
        _point_to(self._offs_arr, b.offsets, n + 1)
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

    def _before_render(self, *_):
        now = time.perf_counter()
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
        self._job = self._buffers.start_visible(
            self.surface, c.GetPosition(), c.GetDirectionOfProjection(),
            bool(c.GetParallelProjection()), tag=self._cam_sig)

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
    def add_structures(self, grid, structures, skip_kinds=("bone",),
                       smooth_iterations: int = 15) -> dict:
        """Mesh every structure of ``grid`` (once) and draw it in its colour.

        Parameters
        ----------
        grid : bonesim.grid.Grid
            Labelled grid (label ``s`` is ``structures[s - 1]``); the initial
            tissue of the case.
        structures : sequence
            Records with ``name``, ``kind`` and ``display_color``.
        skip_kinds : tuple of str
            Kinds not meshed (the bone is the hybrid surface).
        smooth_iterations : int
            Windowed-sinc smoothing passes.

        Returns
        -------
        dict
            Structure name -> triangle count.
        """
        from ..grid import BRICK

        out = {}
        occupied = grid.density > 0
        for s, st in enumerate(structures, start=1):
            if st.kind in skip_kinds:
                continue
            has = np.any((grid.label == s) & occupied, axis=1)
            if not has.any():
                continue
            br = grid.bricks[has]
            lo = br.min(axis=0) * BRICK
            hi = (br.max(axis=0) + 1) * BRICK
            _, lab = grid.to_dense(lo=lo, shape=hi - lo)
            mask = lab == s
            origin = grid.origin_mm + grid.spacing_mm * lo
            pd = structure_polydata(mask, origin, grid.spacing_mm, smooth_iterations)
            self.add_mesh(st.name, pd, st.display_color)
            out[st.name] = int(pd.GetNumberOfPolys())
        return out

    def add_mesh(self, name: str, polydata, color, opacity: float = 1.0):
        """Draw a static mesh (a structure) under ``name``.

        Parameters
        ----------
        name : str
        polydata : vtkPolyData, or (verts (n, 3) float, faces (m, 3) int)
            Geometry [mm].
        color : (3,) int 0-255
        opacity : float
        """
        if isinstance(polydata, tuple):
            polydata = _polydata_from_arrays(*polydata)
        m = vtkPolyDataMapper()
        m.SetInputData(polydata)
        m.ScalarVisibilityOff()
        a = vtkActor()
        a.SetMapper(m)
        p = a.GetProperty()
        p.SetColor(*(np.asarray(color, dtype=float)[:3] / 255.0))
        p.SetOpacity(float(opacity))
        p.SetAmbient(0.15)
        p.SetDiffuse(0.8)
        p.SetSpecular(0.35)
        p.SetSpecularPower(30.0)
        if name in self._structures:
            self.renderer.RemoveActor(self._structures[name])
        self._structures[name] = a
        self.renderer.AddActor(a)
        return a

    def set_structure_visible(self, name: str, visible: bool) -> None:
        """Show or hide one structure mesh."""
        self._structures[name].SetVisibility(bool(visible))

    @property
    def structure_names(self) -> list:
        return list(self._structures)

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
        self._tool_radii = (None, None)
        self.tool_pos_mm = None
        self.tool_axis = np.array([0.0, 0.0, -1.0])
        self._marker = None                            # set_marker builds it
        self.marker_pos_mm = None

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
                 kind: str = "burr") -> None:
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
        """
        pos = np.asarray(pos_mm, dtype=float).reshape(3)
        ax = np.asarray(axis, dtype=float).reshape(3)
        r = float(radius_mm)
        if not (r > 0 and np.all(np.isfinite(pos)) and np.all(np.isfinite(ax))):
            raise ValueError("set_tool needs a finite position and axis and a positive radius")
        self.tool_pos_mm = pos.copy()
        n = np.linalg.norm(ax)
        self.tool_axis = ax / n if n > 0 else np.array([0.0, 0.0, -1.0])
        place = _vtk_matrix(tool_matrix(pos, ax, (1.0, 1.0, 1.0)))
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

    def hide_tool(self) -> None:
        self._burr.SetVisibility(False)
        self._shaft.SetVisibility(False)

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

    # ------------------------------------------------------------------ dust
    def _build_dust(self):
        self._dust_pd = vtkPolyData()
        self._dust_pos = _void_array(vtkFloatArray, 3)
        self._dust_pts = vtkPoints()
        self._dust_pts.SetData(self._dust_pos)
        self._dust_scale = _void_array(vtkFloatArray, 1, "radius")
        self._dust_alpha = _void_array(vtkFloatArray, 1, "opacity")
        self._dust_pd.SetPoints(self._dust_pts)
        self._dust_pd.GetPointData().AddArray(self._dust_scale)
        self._dust_pd.GetPointData().AddArray(self._dust_alpha)
        m = vtkPointGaussianMapper()
        m.SetInputData(self._dust_pd)
        m.SetScaleArray("radius")
        m.SetScaleFactor(1.0)
        m.SetOpacityArray("opacity")
        m.SetEmissive(False)
        m.ScalarVisibilityOff()
        m.SetSplatShaderCode(_DISK_SPLAT)
        a = vtkActor()
        a.SetMapper(m)
        a.GetProperty().SetColor(*DUST_RGB)
        a.GetProperty().SetAmbient(0.4)
        a.GetProperty().SetDiffuse(0.7)
        a.SetVisibility(False)
        a.PickableOff()
        self.renderer.AddActor(a)
        self.dust_actor = a
        self._dust_bufs = None

    def set_dust(self, positions, density, cell_mm: float | None = None) -> None:
        """Show bone dust: one alpha-blended round sprite per dusty cell.

        Parameters
        ----------
        positions : (n, 3) float32
            Cell centres [mm].
        density : (n,) float32
            Fill of each cell (0 empty .. 1 full; larger values are clipped).
        cell_mm : float, optional
            Dust cell edge [mm] (default: the voxel size). A full cell's
            sprite has a radius of 0.7 cell; an emptier one shrinks with the
            cube root of its fill and fades.
        """
        p = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
        d = np.clip(np.asarray(density, dtype=np.float32).reshape(-1), 0.0, 1.0)
        if d.shape[0] != p.shape[0]:
            raise ValueError(f"{p.shape[0]} dust positions but {d.shape[0]} densities")
        keep = d > 0
        if not keep.all():
            p, d = np.ascontiguousarray(p[keep]), d[keep]
        cell = float(self.voxel_mm if cell_mm is None else cell_mm)
        radius = (0.7 * cell * np.cbrt(d)).astype(np.float32)
        alpha = (0.35 + 0.6 * d).astype(np.float32)
        self._dust_bufs = (p, radius, alpha)          # keep the memory alive
        _point_to(self._dust_pos, p, p.size)
        _point_to(self._dust_scale, radius, radius.size)
        _point_to(self._dust_alpha, alpha, alpha.size)
        self._dust_pts.Modified()
        self._dust_pd.Modified()
        self.dust_actor.SetVisibility(p.shape[0] > 0)

    # ------------------------------------------------------------------ text
    def _build_text(self):
        hud = vtkTextActor()
        tp = hud.GetTextProperty()
        tp.SetFontFamilyToCourier()
        tp.SetFontSize(14)
        tp.SetColor(0.95, 0.95, 0.9)
        tp.SetBackgroundColor(0.0, 0.0, 0.0)
        tp.SetBackgroundOpacity(0.35)
        tp.SetVerticalJustificationToBottom()
        hud.SetPosition(8, 8)
        hud.SetVisibility(False)
        self.hud_actor = hud
        self.renderer.AddViewProp(hud)
        hlp = vtkTextActor()
        tp = hlp.GetTextProperty()
        tp.SetFontFamilyToCourier()
        tp.SetFontSize(14)
        tp.SetColor(1.0, 1.0, 0.85)
        tp.SetBackgroundColor(0.0, 0.0, 0.0)
        tp.SetBackgroundOpacity(0.7)
        tp.SetVerticalJustificationToTop()
        hlp.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
        hlp.SetPosition(0.02, 0.97)
        hlp.SetVisibility(False)
        self.help_actor = hlp
        self.renderer.AddViewProp(hlp)

    def set_hud(self, info: dict) -> None:
        """Replace the HUD's values (see :mod:`bonesim.render.hud` for keys).

        Without a ``frame_hz`` entry the scene shows the rate it measures."""
        self._hud_info = dict(info)
        self._draw_hud(time.perf_counter())

    def _font_px(self) -> int:
        """Text size for the window's height: 9 px at 300 rows, 18 px at 600+."""
        h = self.render_window.GetSize()[1] if self.render_window is not None else 600
        return int(np.clip(round(h / 33.0), 9, 18))

    def _draw_hud(self, now):
        fs = self._font_px()
        for a in (self.hud_actor, self.help_actor):
            if a.GetTextProperty().GetFontSize() != fs:
                a.GetTextProperty().SetFontSize(fs)
        self.hud_actor.SetInput(format_hud(self._hud_info, self.frame_hz))
        self.hud_actor.SetVisibility(bool(self._hud_info))
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


def _polydata_from_arrays(verts, faces) -> vtkPolyData:
    v = np.ascontiguousarray(verts, dtype=np.float32).reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    pd = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(numpy_support.numpy_to_vtk(v, deep=True))
    pd.SetPoints(pts)
    cells = vtkCellArray()
    conn = numpy_support.numpy_to_vtkIdTypeArray(f.ravel(), deep=True)
    offs = numpy_support.numpy_to_vtkIdTypeArray(
        np.arange(0, 3 * f.shape[0] + 1, 3, dtype=np.int64), deep=True)
    cells.SetData(offs, conn)
    pd.SetPolys(cells)
    nm = vtkPolyDataNormals()
    nm.SetInputData(pd)
    nm.SplittingOff()
    nm.Update()
    out = vtkPolyData()
    out.DeepCopy(nm.GetOutput())
    return out
