"""The landmarks of a case, drawn from the surgeon's view (``case-info --png``).

The bone is drawn translucent over the landmark groups it hides (the sigmoid
sinus and the dura, split from a merged label where they share one; the
facial nerve, the labyrinth, the middle ear), each in its anatomical colour;
each landmark is a ball coloured by how sure it is (labelled, split from a
merged label, found from geometry, estimated) with its clinical name, and
Macewen's triangle is outlined on the cortex. The camera is the case's.
"""
from __future__ import annotations

import numpy as np

__all__ = ["CONFIDENCE_RGB", "GROUP_CLASS", "GROUP_TEXT", "BONE_OPACITY", "SHEET_OPACITY",
           "landmarks_picture"]

#: Ball colour per landmark confidence (0-255 RGB).
CONFIDENCE_RGB = {"labelled": (255, 255, 255), "split": (0, 230, 255),
                  "found": (60, 230, 90), "estimated": (255, 170, 0)}
#: The anatomical class whose colour draws each landmark group.
GROUP_CLASS = {"sinus": "sigmoid_sinus", "tegmen": "middle_fossa_dura",
               "dura": "posterior_fossa_dura", "facial_nerve": "facial_nerve",
               "labyrinth": "labyrinth", "middle_ear": "ossicles",
               "ear_canal": "ear_canal", "carotid": "carotid_artery",
               "jugular": "jugular_bulb", "iac": "internal_auditory_canal"}
#: What the legend calls each group.
GROUP_TEXT = {"sinus": "Sigmoid sinus", "tegmen": "Tegmen (middle fossa dura)",
              "dura": "Dura", "facial_nerve": "Facial nerve", "labyrinth": "Labyrinth",
              "middle_ear": "Middle ear, ossicles", "ear_canal": "Ear canal",
              "carotid": "Carotid", "jugular": "Jugular bulb",
              "iac": "Internal auditory canal"}
#: Opacity of the bone over the landmarks, and of the sheets of dura and the
#: sinus over the deeper ones.
BONE_OPACITY = 0.22
SHEET_OPACITY = 0.45
#: Landmark ball radius [mm].
BALL_MM = 1.0


def landmarks_picture(case, path, size=(1280, 960)):
    """Draw ``case``'s landmarks from its camera into a PNG.

    Parameters
    ----------
    case : bonesim.io.case.Case
        Loaded or not (its volume is read once).
    path : str or Path
        The picture.
    size : (int, int)
        Width, height [px].

    Returns
    -------
    Path
        The picture written.
    """
    import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text rendering)
    from vtkmodules.vtkFiltersSources import vtkSphereSource
    from vtkmodules.vtkRenderingCore import (vtkActor, vtkBillboardTextActor3D,
                                             vtkPolyDataMapper)

    from bonesim.io.anatomy import load_table
    from bonesim.io.landmarks import analysis_grid
    from bonesim.render.geometry import structure_polydata
    from bonesim.render.scene import Scene
    from bonesim.render.visibility_view import add_legend, legend_font_px

    vol = case.load_volume()
    lm = case.landmarks
    table = load_table()
    h, origin = lm.cortex["h"], lm.cortex["origin_mm"]
    coarse, _, _ = analysis_grid(vol.labels, vol.spacing_mm, vol.origin_mm,
                                 [s.kind for s in case.structures], h)
    bone = np.isin(coarse, [i for i, s in enumerate(case.structures, 1)
                            if s.kind == "bone"])
    scene = Scene(size=size, offscreen=True, visible_subset=False, panel=False)
    try:
        scene.set_hint("")
        drawn = []
        for group, mask in lm.masks.items():
            if not mask.any():
                continue
            cls = table.classes.get(GROUP_CLASS.get(group, ""))
            rgb = cls.colors[0] if cls is not None else (200, 200, 200)
            sheet = group in ("sinus", "tegmen", "dura")
            scene.add_mesh(group, structure_polydata(mask, origin, h, 10), rgb,
                           opacity=SHEET_OPACITY if sheet else 1.0)
            drawn.append((group, rgb))
        scene.add_mesh("bone", structure_polydata(bone, origin, h, 10), (235, 225, 200),
                       opacity=BONE_OPACITY)
        fs = legend_font_px(size[1])
        # the balls and their names on a layer of their own, over everything
        from vtkmodules.vtkRenderingCore import vtkRenderer

        top = vtkRenderer()
        top.SetLayer(1)
        top.SetActiveCamera(scene.renderer.GetActiveCamera())
        top.InteractiveOff()
        scene.render_window.AddRenderer(top)
        for name, m in lm.items.items():
            src = vtkSphereSource()
            src.SetCenter(*m.point_mm)
            src.SetRadius(BALL_MM)
            src.SetThetaResolution(16)
            src.SetPhiResolution(12)
            mp = vtkPolyDataMapper()
            mp.SetInputConnection(src.GetOutputPort())
            a = vtkActor()
            a.SetMapper(mp)
            a.GetProperty().SetColor(*(np.array(CONFIDENCE_RGB[m.confidence]) / 255.0))
            top.AddActor(a)
            t = vtkBillboardTextActor3D()
            t.SetInput(name.replace("_", " "))
            t.SetPosition(*m.point_mm)
            t.SetDisplayOffset(8, 6)
            tp = t.GetTextProperty()
            tp.SetFontSize(fs)
            tp.SetColor(*(np.array(CONFIDENCE_RGB[m.confidence]) / 255.0))
            tp.SetBackgroundColor(0.0, 0.0, 0.0)
            tp.SetBackgroundOpacity(0.5)
            top.AddActor(t)
        mac = lm.get("macewen")
        if mac is not None:
            lat = mac.point_mm[0]
            ring = [(lat, y, z) for y, z in mac.detail["vertices_yz"]]
            top.AddActor(_polyline(np.array(ring + ring[:1], float),
                                   CONFIDENCE_RGB[mac.confidence]))
        cam = case.camera
        scene.set_case_camera(cam.eye_mm, cam.focal_mm, cam.up)
        lines = [(f"{case.name}: landmarks ({case.side} ear, surgeon's view)",
                  (1.0, 1.0, 1.0), fs + 2)]
        lines += [(f"{k}: {v}", np.array(CONFIDENCE_RGB[k]) / 255.0, fs)
                  for k, v in (("labelled", "a structure of its own"),
                               ("split", "split from a merged label"),
                               ("found", "found from the geometry"),
                               ("estimated", "where it must be"))]
        lines += [(GROUP_TEXT.get(g, g), np.array(rgb) / 255.0, fs) for g, rgb in drawn]
        lines += [("missing: " + m, (1.0, 0.55, 0.3), fs) for m in lm.missing]
        add_legend(scene.renderer, lines, size[1] - 8)
        return scene.screenshot(path)
    finally:
        scene.close()


def _polyline(points_mm, rgb):
    """An actor of the polyline through ``points_mm`` (n, 3) [mm]."""
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData, vtkPolyLine
    from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

    pts = vtkPoints()
    line = vtkPolyLine()
    line.GetPointIds().SetNumberOfIds(len(points_mm))
    for i, p in enumerate(points_mm):
        pts.InsertNextPoint(*map(float, p))
        line.GetPointIds().SetId(i, i)
    cells = vtkCellArray()
    cells.InsertNextCell(line)
    pd = vtkPolyData()
    pd.SetPoints(pts)
    pd.SetLines(cells)
    m = vtkPolyDataMapper()
    m.SetInputData(pd)
    a = vtkActor()
    a.SetMapper(m)
    a.GetProperty().SetColor(*(np.asarray(rgb, float) / 255.0))
    a.GetProperty().SetLineWidth(3.0)
    return a
