"""The structures of the 3D scene (nerves, sinus, dura, labyrinth, ...):
meshed once from the case's labels, drawn in their colours, and only their
triangles that can be seen (:mod:`bonesim.render.structure_subset`: those
sealed in tissue are left out until the burr comes near, those turned away
from the camera once it rests). At native resolution (render.toml
``[lod]``) they are meshed on a grid twice as coarse.

:class:`StructuresMixin` is part of :class:`bonesim.render.scene.Scene`; it
uses the scene's ``renderer``, ``style`` and bone ``surface``.
"""
from __future__ import annotations

import numpy as np

from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkTypeInt32Array
from vtkmodules.vtkCommonDataModel import vtkCellArray
from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper
from bonesim.render.geometry import point_to, polydata_from_arrays, structure_polydata
from bonesim.render.structure_subset import SEAL_RADIUS, SealedTriangles, removed_boxes

__all__ = ["StructuresMixin"]


class StructuresMixin:
    """The structures' meshes and drawn subsets of a scene (see the module
    docstring). The scene initialises ``_structures`` (name -> actor),
    ``_sealed`` (name -> drawn subset), ``_coarse_structures`` and
    ``_seal_sig``."""

    def add_structures(self, grid, structures, skip_kinds=("bone",),
                       smooth_iterations: int = 15) -> dict:
        """Mesh every structure of ``grid`` (once) and draw it in its colour.

        Parameters
        ----------
        grid : bonesim.engine.grid.Grid
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
        from bonesim.engine.grid import BRICK

        out = {}
        occupied = grid.density > 0
        lod = self.style.lod
        # level of detail: a native-resolution bone surface gets structures
        # meshed on a grid twice as coarse (render.toml [lod])
        coarse = (lod.max_voxel_px > 0 and self.surface is not None
                  and self.surface.n_triangles >= lod.min_triangles)
        self._coarse_structures = coarse
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
            if coarse:
                # the fraction of each 2x2x2 block inside (bricks are even-sized)
                n = np.array(mask.shape) // 2
                frac = mask.reshape(n[0], 2, n[1], 2, n[2], 2).mean(axis=(1, 3, 5))
                pd = structure_polydata(frac.astype(np.float32), origin + 0.5 * grid.spacing_mm,
                                        2.0 * grid.spacing_mm, smooth_iterations)
            else:
                pd = structure_polydata(mask, origin, grid.spacing_mm, smooth_iterations)
            out[st.name] = int(pd.GetNumberOfPolys())
            a = self.add_mesh(st.name, pd, st.display_color)
            # closed meshes, opaque: their back faces never show
            a.GetProperty().BackfaceCullingOn()
            if self.surface is not None:
                self._seal_structure(st.name, grid, pd)
        return out

    def _seal_structure(self, name, grid, pd):
        """Draw only the triangles of structure ``name`` not sealed inside
        tissue (:mod:`bonesim.render.structure_subset`), through an index
        buffer VTK reads in place."""
        tris = numpy_support.vtk_to_numpy(pd.GetPolys().GetConnectivityArray())
        pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
        sub = SealedTriangles(grid, pts, tris.reshape(-1, 3), self.surface,
                              SEAL_RADIUS + (1 if self._coarse_structures else 0))
        conn, offs = vtkTypeInt32Array(), vtkTypeInt32Array()
        offsets = np.arange(0, 3 * len(sub.tris) + 1, 3, dtype=np.int32)
        cells = vtkCellArray()
        pd.SetPolys(cells)
        self._sealed[name] = (sub, cells, conn, offs, offsets, pd)
        self._seal_sig = None           # turned-away triangles: at the next render
        self._push_sealed(name)

    def _push_sealed(self, name):
        sub, cells, conn, offs, offsets, pd = self._sealed[name]
        point_to(conn, sub.drawn, 3 * sub.n_drawn)
        point_to(offs, offsets, sub.n_drawn + 1)
        cells.SetData(offs, conn)
        cells.Modified()
        pd.Modified()

    def _face_structures(self, sig):
        """The structures' subsets for the camera now (turned-away triangles
        left out; :meth:`SealedTriangles.face`)."""
        c = self.renderer.GetActiveCamera()
        for name, (sub, *_rest) in self._sealed.items():
            sub.face(c.GetPosition(), c.GetDirectionOfProjection(),
                     bool(c.GetParallelProjection()))
            self._push_sealed(name)
        self._seal_sig = sig

    def _unseal_structures(self):
        """Draw every structure triangle again (but those turned away): the
        bone no longer encloses them (body 0 moved off its initial pose)."""
        for name, (sub, *_rest) in list(self._sealed.items()):
            sub.unseal_all()
            self._push_sealed(name)

    def _update_sealed(self, surface, removed, new_surface):
        """Follow the bone surface's changes in the structures' drawn subsets:
        unseal near the removed voxels, or recompute against a new surface
        or unknown changes."""
        boxes = None
        if removed is not None and not new_surface:
            boxes = removed_boxes(removed)            # once for every structure
        for name, (sub, *_rest) in self._sealed.items():
            if getattr(self, "_main_pose", None) is not None:
                changed = False                # unsealed while body 0 is moved
            elif new_surface or removed is None:
                sub.reseal(surface)
                changed = True
            else:
                changed = sub.unseal_near(boxes)
            if changed:
                self._push_sealed(name)

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
            polydata = polydata_from_arrays(*polydata)
        m = vtkPolyDataMapper()
        m.SetInputData(polydata)
        m.ScalarVisibilityOff()
        a = vtkActor()
        a.SetMapper(m)
        p = a.GetProperty()
        p.SetColor(*(np.asarray(color, dtype=float)[:3] / 255.0))
        p.SetOpacity(float(opacity))
        st = self.style.structures
        p.SetAmbient(st.ambient)
        p.SetDiffuse(st.diffuse)
        p.SetSpecular(st.specular)
        p.SetSpecularPower(st.specular_power)
        if name in self._structures:
            self.renderer.RemoveActor(self._structures[name])
        self._sealed.pop(name, None)
        self._structures[name] = a
        self.renderer.AddActor(a)
        return a

    def set_structure_visible(self, name: str, visible: bool) -> None:
        """Show or hide one structure mesh."""
        self._structures[name].SetVisibility(bool(visible))

    @property
    def structure_names(self) -> list:
        return list(self._structures)
