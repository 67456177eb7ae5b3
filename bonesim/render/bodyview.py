"""Every body of the bone drawn at its pose (part of :class:`~bonesim.render.scene.Scene`).

A case's bone is a set of bodies (:mod:`bonesim.engine.bodies`); after a split
a :class:`~bonesim.engine.replica.TissueReplica` keeps one surface per body, in
the body's own frame (:attr:`~bonesim.engine.replica.TissueReplica.body_surfaces`),
and the body's pose places it in the case frame
(:meth:`~bonesim.engine.replica.TissueReplica.body_matrix`).
:meth:`BodiesMixin.update_bodies` draws them:

* body 0 (the main bone) is the scene's surface actor, drawn as before
  (zero-copy vertex arrays, visible subset; :meth:`Scene.update_surface`),
  with body 0's pose as the actor's user matrix when it is not the
  identity. The visible subset is computed in body 0's frame (the camera is
  taken into it), and a change of body 0's pose counts as a camera move;
* every other body (a fragment) gets an actor of its own: a copy of its
  surface's compact arrays, refreshed only when the replica reports that
  body's surface changed (fragments are small), with the body's pose as
  user matrix and the bone's material, its colours tinted by
  :func:`fragment_tint` so that each fragment reads as a piece of its own.
  Actors come and go with the bodies (a reset drops them all);
* plates and distractors (the replica's ``plates``, from ``PLATE`` events,
  :mod:`bonesim.engine.rigid_set`) are drawn from the catalogue's meshes
  (:mod:`bonesim.io.plates`) at their poses, in titanium grey.

Units: positions [mm], case frame after the user matrix.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkCommonMath import vtkMatrix4x4
from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

from bonesim.render.meshbuf import oriented_triangles

__all__ = ["BodiesMixin", "vtk_matrix", "surface_polydata", "FRAGMENT_TINTS",
           "fragment_tint", "PLATE_COLOR", "mesh_polydata", "light_by_outward_normals",
           "OUTWARD_NORMAL_IMPL"]

_IDENTITY = np.eye(4)
#: Per-channel factors on a fragment's colours, by body id (body 1 the first,
#: repeating): warm orange, sky blue, leaf green, rose, straw. Strong enough
#: to tell a fragment from the bone around it, weak enough to keep the bone's
#: shading and the structures' colours readable.
FRAGMENT_TINTS = ((1.0, 0.72, 0.45), (0.55, 0.78, 1.0), (0.62, 1.0, 0.55),
                  (1.0, 0.6, 0.8), (1.0, 0.95, 0.45))
#: Colour of plates and distractors (titanium), RGB 0-1.
PLATE_COLOR = (0.66, 0.69, 0.74)


#: Fragment-shader code that takes a bone surface's normals as they are. VTK
#: turns the normals of back-facing triangles around (two-sided lighting);
#: the bone's vertex normals always point out of the bone (the smoothed
#: density's gradient), and a triangle seen edge-on at a rim can be
#: back-facing on screen while its normals face the eye: turned around, it
#: would be a dark speck. Replaces VTK's ``//VTK::Normal::Impl`` (before VTK's
#: own code, which then finds no tag to fill).
OUTWARD_NORMAL_IMPL = "vec3 normalVCVSOutput = normalize(normalVCVSOutput);\n"


def light_by_outward_normals(actor) -> None:
    """Light ``actor``'s surface by its point normals on both faces,
    without turning them around on back faces (:data:`OUTWARD_NORMAL_IMPL`)."""
    actor.GetShaderProperty().AddFragmentShaderReplacement(
        "//VTK::Normal::Impl", True, OUTWARD_NORMAL_IMPL, False)


def fragment_tint(b: int) -> tuple:
    """The tint of body ``b`` (None for body 0, the main bone)."""
    return None if b == 0 else FRAGMENT_TINTS[(b - 1) % len(FRAGMENT_TINTS)]


def vtk_matrix(m) -> vtkMatrix4x4:
    """A ``vtkMatrix4x4`` of a (4, 4) array_like (row-major, [mm] translation)."""
    a = np.asarray(m, dtype=np.float64).reshape(4, 4)
    out = vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            out.SetElement(r, c, float(a[r, c]))
    return out


def surface_polydata(surface, tint=None) -> vtkPolyData:
    """A deep copy of a :class:`~bonesim.engine.surface.Surface` as polydata:
    points [mm], its normals and RGBA colours as point data, its triangles
    wound as the scene draws them (:func:`bonesim.render.meshbuf.oriented_triangles`).
    ``tint`` (3 factors 0-1) scales the colours' RGB."""
    pos, nrm, col, tri = surface.arrays()
    tri = oriented_triangles(pos, nrm, tri)
    if tint is not None:
        col = np.array(col, copy=True)
        col[:, :3] = np.clip(col[:, :3] * np.asarray(tint, float), 0, 255).astype(np.uint8)
    return mesh_polydata(pos, tri, nrm, col)


def mesh_polydata(pos, tri, nrm, col=None) -> vtkPolyData:
    """Polydata of a triangle mesh: points [mm], normals, optional RGBA
    colours (n, 4) uint8, triangles (m, 3)."""
    pd = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(pos), deep=True))
    pd.SetPoints(pts)
    n = numpy_support.numpy_to_vtk(np.ascontiguousarray(nrm), deep=True)
    n.SetName("Normals")
    pd.GetPointData().SetNormals(n)
    if col is not None:
        c = numpy_support.numpy_to_vtk(np.ascontiguousarray(col), deep=True,
                                       array_type=numpy_support.get_vtk_array_type(np.uint8))
        c.SetName("Colors")
        pd.GetPointData().SetScalars(c)
    cells = vtkCellArray()
    conn = numpy_support.numpy_to_vtkIdTypeArray(
        np.ascontiguousarray(tri, dtype=np.int64).ravel(), deep=True)
    offs = numpy_support.numpy_to_vtkIdTypeArray(
        np.arange(0, 3 * len(tri) + 1, 3, dtype=np.int64), deep=True)
    cells.SetData(offs, conn)
    pd.SetPolys(cells)
    return pd


class BodiesMixin:
    """Bodies at their poses (see the module docstring). Mixed into
    :class:`~bonesim.render.scene.Scene`, which provides ``renderer``,
    ``surface_actor`` and :meth:`update_surface`."""

    def _build_bodies(self) -> None:
        self._body_actors: dict = {}      # body id -> (actor, surface, revision)
        self._plate_actors: dict = {}     # plate slot -> (actor, catalogue index)
        self._main_pose = None            # body 0's (4, 4) pose, None for the identity

    @property
    def body_actors(self) -> dict:
        """Body id -> the ``vtkActor`` of each drawn body other than 0."""
        return {b: a for b, (a, _, _) in self._body_actors.items()}

    def update_bodies(self, replica, removed=None, touched=None) -> dict:
        """Draw every body of ``replica`` at its pose (call after each
        ``replica.apply`` / ``drain``, instead of :meth:`update_surface`).

        Parameters
        ----------
        replica : bonesim.engine.replica.TissueReplica
            With a surface.
        removed, touched : (n, 3) int array_like, optional
            For body 0's visible subset, as for :meth:`update_surface`: every
            voxel given to a surface update since the previous call, i.e.
            ``Changes.changed`` (removed and split off) and
            ``Changes.touched``; None if unknown.

        Returns
        -------
        dict
            :meth:`update_surface`'s, plus ``bodies`` (bodies drawn) and
            ``rebuilt`` (fragment actors refreshed by this call).
        """
        surfaces = replica.body_surfaces
        if 0 not in surfaces:
            raise ValueError("the replica keeps no surface (make it with surface=True)")
        self._set_main_pose(replica.body_matrix(0))
        out = self.update_surface(surfaces[0], removed, touched)
        revs = replica.body_revisions
        for b in [b for b in self._body_actors if b not in surfaces or b == 0]:
            self.renderer.RemoveActor(self._body_actors.pop(b)[0])
        rebuilt = 0
        for b, surf in surfaces.items():
            if b == 0:
                continue
            rebuilt += self._draw_body(b, surf, revs.get(b), replica.body_matrix(b))
        out["bodies"] = len(surfaces)
        out["rebuilt"] = rebuilt
        out["plates"] = self.update_plates(getattr(replica, "plates", None) or {})
        return out

    @property
    def plate_actors(self) -> dict:
        """Plate slot -> the ``vtkActor`` of each drawn plate or distractor."""
        return {s: a for s, (a, _) in self._plate_actors.items()}

    def update_plates(self, plates: dict) -> int:
        """Draw the plates ``slot -> (catalogue index, (7,) pose, host)`` at
        their poses (mesh-to-case); returns how many are drawn."""
        from bonesim.engine.bodies import pose_matrix
        from bonesim.io.plates import default_plates

        for s in [s for s in self._plate_actors if s not in plates]:
            self.renderer.RemoveActor(self._plate_actors.pop(s)[0])
        for s, (cat, pose, _) in plates.items():
            entry = self._plate_actors.get(s)
            if entry is None or entry[1] != cat:
                if entry is not None:
                    self.renderer.RemoveActor(entry[0])
                spec = default_plates()[cat]
                mapper = vtkPolyDataMapper()
                mapper.SetInputData(mesh_polydata(spec.pos, spec.tris, spec.nrm))
                mapper.ScalarVisibilityOff()
                actor = vtkActor()
                actor.SetMapper(mapper)
                prop = actor.GetProperty()
                prop.SetColor(*PLATE_COLOR)
                prop.SetSpecular(0.6)
                prop.SetSpecularPower(40.0)
                prop.SetDiffuse(0.8)
                prop.SetAmbient(0.2)
                self.renderer.AddActor(actor)
                self._plate_actors[s] = entry = (actor, cat)
            m = np.eye(4)
            m[:3] = pose_matrix(pose)
            entry[0].SetUserMatrix(vtk_matrix(m))
        return len(self._plate_actors)

    def _set_main_pose(self, m) -> None:
        m = np.asarray(m, dtype=np.float64)
        pose = None if np.array_equal(m, _IDENTITY) else m.copy()
        old = self._main_pose
        if (pose is None) == (old is None) and (pose is None or np.array_equal(pose, old)):
            return
        self._main_pose = pose
        self.surface_actor.SetUserMatrix(None if pose is None else vtk_matrix(pose))
        if pose is not None:
            # the structures stay where they are: no longer inside the bone
            self._unseal_structures()
        self._cam_sig = None              # the view of body 0 changed: like a camera move

    def _to_main_frame(self, eye, direction):
        """Camera eye [mm] and view direction, case frame -> body 0's frame."""
        if self._main_pose is None:
            return eye, direction
        r, t = self._main_pose[:3, :3], self._main_pose[:3, 3]
        return (tuple((np.asarray(eye) - t) @ r), tuple(np.asarray(direction) @ r))

    def _draw_body(self, b: int, surf, revision, matrix) -> int:
        """Create or refresh body ``b``'s actor; returns 1 if its geometry was
        copied again."""
        entry = self._body_actors.get(b)
        fresh = entry is None or entry[1] is not surf or entry[2] != revision
        if entry is None:
            mapper = vtkPolyDataMapper()
            mapper.SetColorModeToDirectScalars()
            mapper.SetScalarModeToUsePointData()
            mapper.ScalarVisibilityOn()
            actor = vtkActor()
            actor.SetMapper(mapper)
            actor.ForceOpaqueOn()
            actor.SetProperty(self.surface_actor.GetProperty())     # the bone's material
            light_by_outward_normals(actor)
            self.renderer.AddActor(actor)
        else:
            actor = entry[0]
        if fresh:
            actor.GetMapper().SetInputData(surface_polydata(surf, fragment_tint(b)))
        actor.SetUserMatrix(vtk_matrix(matrix))
        self._body_actors[b] = (actor, surf, revision)
        return int(fresh)
