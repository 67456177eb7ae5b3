"""Rendering a recorded run as a vision dataset: RGB, depth, segmentation,
normals, point clouds and cameras of every frame, offscreen.

:class:`DatasetRenderer` draws a :class:`~bonesim.session.dataset_frames.FrameState`
(the tissue, tool, dust, water and suction tool of one moment, from
:mod:`bonesim.session.dataset_frames`) on a :class:`~bonesim.render.scene.Scene`
twice per eye:

1. **The picture**: the scene as the window draws it (the HUD and the hidden
   burr's silhouette only on request), read back as RGB.
2. **The label pass**: every drawn object in one flat colour that encodes
   an entry of a table (what it is: a body's bone surface, a structure's
   mesh, the burr, the shaft, the suction tool, dust, water, a plate), no
   lighting, no custom shader code, no blending, no HUD; dust and water sprites drawn opaque over
   their cores (:data:`~bonesim.session.dataset_spec.SPRITE_LABEL_OPACITY`).
   The colour buffer gives each pixel's entry and the depth buffer the
   first surface's depth, turned into metric depth along the optical axis
   with the projection the frame was drawn with. On tissue (a body's bone
   surface, or a structure's own mesh) the structure is the one of the voxel
   the pixel's ray reaches there
   (:func:`bonesim.session.dataset_labels.label_image`, in the body's
   frame), so the labels follow the voxels where the smoothed meshes and the
   bone's surface cross within a voxel of each other.

Both passes draw the same geometry with the same camera, so the labels and
the depth describe the picture's pixels; the intrinsics and extrinsics are
read from the camera VTK drew with (:mod:`bonesim.session.dataset_camera`,
OpenCV convention). Rendering is deterministic: no visible-subset thread, no
anti-aliasing, one fixed order of work.

:func:`make_dataset` renders a session file into a dataset file or folder
(:mod:`bonesim.session.dataset_io`).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkFloatArray, vtkPoints
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkRenderingCore import (vtkActor, vtkPointGaussianMapper, vtkProp3D,
                                         vtkProperty, vtkShaderProperty)

from bonesim.session import dataset_spec as spec
from bonesim.session.dataset_camera import (cam_to_case, depth_from_zbuffer,
                                            normals_from_points, opencv_extrinsics,
                                            opencv_intrinsics, pixel_rays)
from bonesim.session.dataset_labels import label_image

__all__ = ["ID_SPLAT_SHADER", "DatasetRenderer", "make_dataset"]

#: Fragment code of a dust or water sprite in the label pass: an opaque disc
#: of the sprite's core radius in the property's flat colour.
ID_SPLAT_SHADER = (
    "//VTK::Color::Impl\n"
    "if (dot(offsetVCVSOutput.xy, offsetVCVSOutput.xy) > 1.0) { discard; }\n"
    "diffuseColor = vec3(0.0);\n"
    "opacity = 1.0;\n")

_TISSUE, _STRUCTURE, _FIXED = "tissue", "structure", "fixed"


def _matrix(m4) -> np.ndarray:
    return np.array([[m4.GetElement(r, c) for c in range(4)] for r in range(4)])


def _code_rgb(k: int) -> tuple:
    return ((k & 255) / 255.0, ((k >> 8) & 255) / 255.0, ((k >> 16) & 255) / 255.0)


def _flat_property(k: int) -> vtkProperty:
    p = vtkProperty()
    p.SetColor(*_code_rgb(k))
    p.SetAmbient(1.0)
    p.SetDiffuse(0.0)
    p.SetSpecular(0.0)
    p.LightingOff()
    p.SetOpacity(1.0)
    return p


class _IdSprites:
    """An opaque stand-in for a dust or water layer in the label pass: one
    disc per sprite whose opacity reaches the label threshold, of the radius
    within which it does."""

    def __init__(self, renderer):
        self.polydata = vtkPolyData()
        self._pts = vtkPoints()
        self._pos = vtkFloatArray()
        self._pos.SetNumberOfComponents(3)
        self._pts.SetData(self._pos)
        self._radius = vtkFloatArray()
        self._radius.SetName("radius")
        self.polydata.SetPoints(self._pts)
        self.polydata.GetPointData().AddArray(self._radius)
        m = vtkPointGaussianMapper()
        m.SetInputData(self.polydata)
        m.SetScaleArray("radius")
        m.SetScaleFactor(1.0)
        m.SetEmissive(False)
        m.ScalarVisibilityOff()
        m.SetSplatShaderCode(ID_SPLAT_SHADER)
        a = vtkActor()
        a.SetMapper(m)
        a.ForceOpaqueOn()
        a.SetVisibility(False)
        a.PickableOff()
        renderer.AddActor(a)
        self.actor = a
        self._bufs = None

    def set(self, bufs, k: int) -> int:
        """Show the cores of the layer's sprites ``bufs = (positions, radius,
        rgba)`` in colour ``k``; returns how many."""
        if bufs is None:
            self.actor.SetVisibility(False)
            return 0
        pos, radius, rgba = bufs
        alpha = np.asarray(rgba, np.float64)[:, 3] / 255.0
        keep = alpha >= spec.SPRITE_LABEL_OPACITY
        if not keep.any():
            self.actor.SetVisibility(False)
            return 0
        # (1 - r^2)^2 * alpha >= A  <=>  r^2 <= 1 - sqrt(A / alpha)
        core = np.sqrt(np.maximum(1.0 - np.sqrt(spec.SPRITE_LABEL_OPACITY / alpha[keep]), 0.0))
        p = np.ascontiguousarray(np.asarray(pos, np.float32)[keep])
        r = np.ascontiguousarray((np.asarray(radius, np.float64)[keep] * core)
                                 .astype(np.float32))
        self._bufs = (p, r)
        self._pos.SetVoidArray(p, int(p.size), 1)
        self._radius.SetVoidArray(r, int(r.size), 1)
        self._pos.Modified()
        self._radius.Modified()
        self._pts.Modified()
        self.polydata.Modified()
        self.actor.SetProperty(_flat_property(k))
        self.actor.SetVisibility(True)
        return int(len(p))


class DatasetRenderer:
    """Renders :class:`~bonesim.session.dataset_frames.FrameState` s of one player.

    Parameters
    ----------
    player : bonesim.session.playback.Player
    options : bonesim.session.dataset_spec.DatasetOptions

    Attributes
    ----------
    scene : Scene
        Offscreen, ``options.size``, no side panel, every triangle drawn.
    stats : dict
        ``label_misses`` (bone pixels whose ray found no voxel), frames.
    """

    def __init__(self, player, options):
        from bonesim.render.scene import Scene

        self.player = player
        self.options = options
        self.model = player.model
        self.scene = Scene.from_model(player.model, player.surface, offscreen=True,
                                      size=tuple(options.size), visible_subset=False,
                                      panel=False, title="bonesim dataset")
        sc = self.scene
        if not options.hud:
            sc.set_hud({})
            sc.set_hint("")
        self._names = {st.name: s for s, st in enumerate(player.model.structures, start=1)}
        self._plain_shading = vtkShaderProperty()
        self._id_dust = _IdSprites(sc.renderer)
        self._id_water = _IdSprites(sc.renderer)
        self._drawn = None
        self._rays = None
        self.stats = {"label_misses": 0, "frames": 0}

    def close(self) -> None:
        if self.scene is not None:
            self.scene.close()
            self.scene = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------- the scene
    def _show(self, fs) -> None:
        """Put the frame's tissue, tool, dust, water and suction tool on the scene."""
        from bonesim.session.playback import hud_info

        sc, p, f = self.scene, self.player, fs.frame
        sc.update_bodies(p.replica)         # bodies at their poses, surfaces as they are
        self._drawn = p.surface
        r = float(getattr(f.burr, "radius_mm", 1.0))
        depth = None
        if self.options.hud:
            from bonesim.physics.sightline import depth_below_surface_mm

            depth = depth_below_surface_mm(p.grid, f.pos_mm, fs.cameras[0][0], r)
        sc.set_tool(f.pos_mm, f.axis, r, f.drill, depth_mm=depth)
        if fs.suction is not None:
            sc.set_suction(*fs.suction)
        else:
            sc.set_suction(None)
        if fs.dust is not None:
            sc.set_dust(*fs.dust)
        if fs.water is not None:
            sc.set_water(*fs.water)
        elif getattr(sc, "water", None) is not None:
            sc.set_water(np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
        if self.options.hud:
            info = hud_info(f, self.model)
            info["frame_hz"] = None
            if fs.irrigation:
                info["irrigation"] = True
            sc.set_hud(info)

    def _set_camera(self, eye, focal, up):
        self.scene.set_camera(eye, focal, up)

    def _camera_now(self) -> dict:
        """Intrinsics and extrinsics of the camera the last frame was drawn with."""
        cam = self.scene.camera
        w, h = self.options.size
        proj = _matrix(cam.GetProjectionTransformMatrix(w / h, -1.0, 1.0))
        r, t = opencv_extrinsics(_matrix(cam.GetViewTransformMatrix()))
        return {"K": opencv_intrinsics(proj, (w, h)), "R": r, "t": t,
                "cam_to_case": cam_to_case(r, t), "projection": proj,
                "eye_mm": np.array(cam.GetPosition()),
                "focal_mm": np.array(cam.GetFocalPoint()), "up": np.array(cam.GetViewUp())}

    # ---------------------------------------------------------- label pass
    def _entries(self):
        """(actor, entry) for every visible 3D actor of the view, and the
        layers drawn as sprites; an entry is ``(kind, class id, instance)``."""
        sc = self.scene
        known = {id(sc.surface_actor): (_TISSUE, None, 0)}
        for b, a in sc.body_actors.items():
            known[id(a)] = (_TISSUE, None, int(b))
        for name, a in sc._structures.items():
            known[id(a)] = (_STRUCTURE, self._names.get(name, spec.CLASS_OTHER), 0)
        known[id(sc._burr)] = (_FIXED, spec.CLASS_BURR, spec.NO_INSTANCE)
        known[id(sc._shaft)] = (_FIXED, spec.CLASS_SHAFT, spec.NO_INSTANCE)
        if sc._suction is not None:
            known[id(sc._suction)] = (_FIXED, spec.CLASS_SUCTION, spec.NO_INSTANCE)
        for s, a in sc.plate_actors.items():
            known[id(a)] = (_FIXED, spec.CLASS_PLATE, int(s))
        hide = {id(sc.dust.actor), id(self._id_dust.actor), id(self._id_water.actor)}
        water = getattr(sc, "water", None)
        if water is not None:
            hide.add(id(water.actor))
        for extra in ("_marker", "_ghost_burr", "_ghost_neck"):
            a = getattr(sc, extra, None)
            if a is not None:
                hide.add(id(a))
        cut = getattr(sc, "cut_plane", None)
        if cut is not None:
            for a in vars(cut).values():
                if isinstance(a, vtkProp3D):
                    hide.add(id(a))
        out, hidden2d = [], []
        props = sc.renderer.GetViewProps()
        props.InitTraversal()
        for _ in range(props.GetNumberOfItems()):
            a = props.GetNextProp()
            if not a.GetVisibility():
                continue
            if not isinstance(a, vtkProp3D):
                hidden2d.append(a)           # HUD, hint, help: never labelled
                continue
            if id(a) in hide:
                continue
            out.append((a, known.get(id(a), (_FIXED, spec.CLASS_OTHER, spec.NO_INSTANCE))))
        return out, hidden2d

    def _label_pass(self):
        """Render every object flat in its entry's colour; returns the entry
        table, the (H, W) entry index per pixel (0 background) and the depth
        buffer (H, W) (first row at the top)."""
        sc = self.scene
        ren = sc.renderer
        w, h = self.options.size
        actors, hidden2d = self._entries()
        table = [None]
        saved = []
        for a, entry in actors:
            table.append(entry)
            k = len(table) - 1
            m = a.GetMapper()
            saved.append((a, a.GetProperty(), m.GetScalarVisibility(), a.GetForceOpaque(),
                          a.GetForceTranslucent(), a.GetShaderProperty()))
            a.SetProperty(_flat_property(k))
            a.SetShaderProperty(self._plain_shading)     # no custom shader code
            m.ScalarVisibilityOff()
            a.ForceOpaqueOn()
            a.ForceTranslucentOff()
        sprite_layers = [(sc.dust, self._id_dust, spec.CLASS_DUST)]
        water = getattr(sc, "water", None)
        if water is not None:
            sprite_layers.append((water, self._id_water, spec.CLASS_WATER))
        layers_vis = []
        for layer, ids, cid in sprite_layers:
            vis = layer.actor.GetVisibility()
            layers_vis.append((layer.actor, vis))
            if vis:
                table.append((_FIXED, cid, spec.NO_INSTANCE))
                if not ids.set(getattr(layer, "_bufs", None), len(table) - 1):
                    table.pop()
            layer.actor.SetVisibility(False)
        for a in hidden2d:
            ren.RemoveViewProp(a)
        bg = ren.GetBackground()
        ren.SetBackground(0.0, 0.0, 0.0)
        ov = sc.overlay_renderer
        ov_draw = ov.GetDraw()
        ov.DrawOff()
        try:
            img = sc.image()
            z = vtkFloatArray()
            sc.render_window.GetZbufferData(0, 0, w - 1, h - 1, z)
            zb = numpy_support.vtk_to_numpy(z).reshape(h, w)[::-1].copy()
        finally:
            ov.SetDraw(ov_draw)
            ren.SetBackground(*bg)
            for a in hidden2d:
                ren.AddViewProp(a)
            for a, vis in layers_vis:
                a.SetVisibility(vis)
            self._id_dust.actor.SetVisibility(False)
            self._id_water.actor.SetVisibility(False)
            for a, prop, sv, fo, ft, sh in saved:
                a.SetProperty(prop)
                a.SetShaderProperty(sh)
                a.GetMapper().SetScalarVisibility(sv)
                a.SetForceOpaque(fo)
                a.SetForceTranslucent(ft)
        idx = (img[..., 0].astype(np.int64) | (img[..., 1].astype(np.int64) << 8)
               | (img[..., 2].astype(np.int64) << 16))
        if idx.max() >= len(table):
            raise RuntimeError(f"label pass: pixel code {int(idx.max())} is not one of the "
                               f"{len(table) - 1} objects drawn (blending or shading on?)")
        return table, idx, zb

    def _classes(self, table, idx, depth, cam):
        """``class`` (H, W) uint8 and ``instance`` (H, W) int16 of the label pass."""
        n = len(table)
        cls_of = np.zeros(n, np.uint8)
        inst_of = np.full(n, spec.NO_INSTANCE, np.int16)
        entry_body = np.full(n, -1, np.int64)
        fallback = np.zeros(n, np.uint8)
        for k, e in enumerate(table[1:], start=1):
            kind, cid, inst = e
            inst_of[k] = inst
            if kind == _TISSUE:
                entry_body[k] = inst
            elif kind == _STRUCTURE:         # its voxels decide, as for the bone's
                entry_body[k] = inst
                fallback[k] = cid
            else:
                cls_of[k] = cid
        cls = cls_of[idx]
        inst = inst_of[idx]
        if (entry_body >= 0).any():
            st = self.player.replica.state
            self.stats["label_misses"] += label_image(
                self.player.grid, st.body, st.pose_m, entry_body, idx, depth, cam["K"],
                cam["R"], cam["cam_to_case"][:3, 3], cls, fallback)
        return cls, inst

    def _pixel_rays(self, k):
        if self._rays is None or not np.array_equal(self._rays[0], k):
            self._rays = (k.copy(), pixel_rays(k, self.options.size))
        return self._rays[1]

    # -------------------------------------------------------------- frames
    def render(self, fs) -> list[dict]:
        """Every stream of one frame, per eye.

        Returns
        -------
        list of dict
            One per eye (left first): ``camera`` (``K``, ``R``, ``t``,
            ``cam_to_case``, ``eye_mm``, ``focal_mm``, ``up``), and the
            streams the options ask for: ``rgb`` (H, W, 3) uint8, ``depth``
            (H, W) float32 [mm] (NaN: nothing), ``class`` (H, W) uint8,
            ``instance`` (H, W) int16, ``normals`` (H, W, 3) float32 (camera
            frame), ``points_cam`` / ``points_case`` (H, W, 3) float32 [mm].
        """
        o = self.options
        self._show(fs)
        sc = self.scene
        out = []
        for eye, focal, up in fs.cameras:
            self._set_camera(eye, focal, up)
            res = {}
            ov = sc.overlay_renderer
            if o.rgb:
                if not o.hud:
                    ov.DrawOff()
                try:
                    res["rgb"] = sc.image()
                finally:
                    ov.DrawOn()
            if o.needs_labels:
                table, idx, zb = self._label_pass()
                cam = self._camera_now()
                depth = depth_from_zbuffer(zb, cam["projection"])
                if o.depth:
                    res["depth"] = depth
                if o.seg:
                    res["class"], res["instance"] = self._classes(table, idx, depth, cam)
                if o.normals or o.points:
                    pts = (self._pixel_rays(cam["K"]) * depth[..., None]).astype(np.float32)
                    if o.normals:
                        res["normals"] = normals_from_points(pts)
                    if o.points:
                        res["points_cam"] = pts
                        m = cam["cam_to_case"]
                        res["points_case"] = (pts.astype(np.float64) @ m[:3, :3].T
                                              + m[:3, 3]).astype(np.float32)
            else:
                cam = self._camera_now()
            res["camera"] = {k: v for k, v in cam.items() if k != "projection"}
            out.append(res)
        self.stats["frames"] += 1
        return out


def frame_record(fs, session_t0: float) -> dict:
    """The per-frame values written beside the images (tool, drill, burr,
    removed voxels, time): a :class:`FrameState` as numbers."""
    f = fs.frame
    ax = np.asarray(f.axis, float)
    n = np.linalg.norm(ax)
    suction = np.full(3, np.nan) if fs.suction is None else np.asarray(fs.suction[0], float)
    return {"t_s": float(f.t_s), "session_t_s": float(session_t0 + f.t_s),
            "sample": int(f.index), "epoch": int(f.epoch),
            "tool_pos_mm": np.asarray(f.pos_mm, float), "tool_axis": ax / n if n else ax,
            "burr": int(f.burr_index), "burr_radius_mm": float(getattr(f.burr, "radius_mm",
                                                                        np.nan)),
            "drill": int(bool(f.drill)), "speed_rpm": float(f.speed_rpm),
            "direction": int(f.direction), "force_n": float(f.force_n),
            "removed_voxels": int(f.voxels_removed), "suction_tip_mm": suction,
            "irrigation": int(bool(fs.irrigation))}


def make_dataset(run, out, options, *, progress=None) -> dict:
    """Render a recorded run into a dataset (an HDF5 file, or a folder).

    Parameters
    ----------
    run : path or Session
        The recording.
    out : path
        ``*.h5`` / ``*.hdf5``: one HDF5 file; anything else: a folder of
        images with ``index.json`` (``docs/dataset_format.md``).
    options : DatasetOptions
    progress : callable, optional
        ``progress(done, total)`` after each frame.

    Returns
    -------
    dict
        Summary: ``out``, ``frames``, ``size``, ``eyes``, ``wall_s``,
        ``frames_per_s``, ``label_misses``.
    """
    from bonesim.session.dataset_frames import FrameSource
    from bonesim.session.dataset_io import open_writer
    from bonesim.session.reader import damage_notice, read_session

    from bonesim.errors import BonesimError

    session = read_session(run) if isinstance(run, (str, Path)) else run
    notes = []
    line = damage_notice(session) if hasattr(session, "damage") else None
    if line:
        notes.append(line)
    try:
        src = FrameSource(session, options)
    except BonesimError as exc:              # a bad --start/--end: name the run too
        if exc.path is not None or getattr(session, "path", None) is None:
            raise
        raise BonesimError(exc.message, session.path, exc.field) from None
    n = len(src.times)
    prov = spec.provenance(session, options, n, notes)
    classes = spec.class_table(src.player.model.structures)
    burrs = [str(getattr(b, "name", "?")) for b in src.player.burrs]
    t0 = time.perf_counter()
    with open_writer(out, options, n, classes, prov, burrs) as wr, \
            DatasetRenderer(src.player, options) as rend:
        for i, fs in enumerate(src):
            eyes = rend.render(fs)
            wr.write(i, frame_record(fs, src.player.timeline.t0), eyes)
            if progress is not None:
                progress(i + 1, n)
    wall = time.perf_counter() - t0
    return {"out": str(out), "frames": n, "size": list(options.size),
            "eyes": list(options.eyes), "wall_s": round(wall, 3),
            "frames_per_s": round(n / wall, 3) if wall > 0 else 0.0,
            "label_misses": rend.stats["label_misses"], "notes": notes}
