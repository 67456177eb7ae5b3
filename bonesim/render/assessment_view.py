"""The assessment view: a run's cavity from the surgeon's eye, each item of the
final-product assessment marked where it was measured (``bonesim assess
--png``).

The bone left at the end is drawn as a smooth surface (the cavity shows as
the hole in it), the structures that are not bone in their colours; each
scored item's region (the thinned or exposed part of a plate, the overhang,
the antrum, the drilled part of a nerve...) is drawn over everything as small
cubes coloured by its outcome (green done, amber partial, red missed or
violated) and numbered at its anchor; the legend lists the items with their
scores in the same colours. The arrays come from :mod:`metrics.assessment`.
"""
from __future__ import annotations

import numpy as np

__all__ = ["OUTCOME_RGB", "BONE_RGB", "BONE_OPACITY", "REGION_OPACITY", "ZOOM",
           "assessment_picture"]

#: Colour per outcome (0-255 RGB).
OUTCOME_RGB = {"done": (40, 200, 60), "partial": (255, 170, 0), "missed": (230, 40, 30),
               "violated": (230, 40, 30), "n/a": (150, 150, 150)}
#: The bone's colour and opacity (slightly translucent: thinned plates show).
BONE_RGB = (235, 225, 200)
BONE_OPACITY = 0.9
#: Opacity of the items' regions.
REGION_OPACITY = 0.75
#: A region cube's edge as a share of the voxel edge.
CUBE_FILL = 0.8
#: The camera comes this many times closer to the focal point than the case
#: camera (the cavity fills the frame, as in the headless main job).
ZOOM = 1.5


def assessment_picture(path, present, labels, spacing_mm: float, origin_mm, structures,
                       items, camera, title: str, size=(1280, 960)):
    """Draw the assessment view into a PNG, offscreen.

    Parameters
    ----------
    path : str or Path
    present : (nx, ny, nz) bool
        Tissue left at the end, axes x, y, z of the case frame.
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s >= 1`` is ``structures[s - 1]``).
    spacing_mm : float
        Voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    structures : sequence
        Records with ``name``, ``kind`` and ``display_color``.
    items : sequence
        Records with ``title``, ``score`` (int or None), ``outcome``,
        ``region_mm`` ((n, 3) [mm]) and ``anchor_mm`` ((3,) [mm] or None)
        (:class:`metrics.assessment.ItemResult`).
    camera : (eye_mm, focal_mm, up)
        The surgeon's view, case frame [mm].
    title : str
        First legend line.
    size : (int, int)
        Width, height [px].

    Returns
    -------
    Path
    """
    import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text rendering)
    from vtkmodules.vtkRenderingCore import vtkBillboardTextActor3D, vtkRenderer

    from bonesim.io.anatomy import clinical_name
    from bonesim.render.geometry import structure_polydata
    from bonesim.render.scene import Scene
    from bonesim.render.visibility_view import cubes_actor, add_legend, legend_font_px

    present = np.asarray(present, bool)
    labels = np.asarray(labels)
    origin = np.asarray(origin_mm, float)
    h = float(spacing_mm)
    scene = Scene(size=tuple(size), offscreen=True, visible_subset=False, panel=False)
    try:
        scene.set_hint("")
        drawn = []
        for s, st in enumerate(structures, start=1):
            if st.kind == "bone":
                continue
            m = present & (labels == s)
            if m.any():
                scene.add_mesh(st.name, structure_polydata(m, origin, h, 10),
                               st.display_color)
                drawn.append(st)
        bone_ids = [s for s, st in enumerate(structures, start=1) if st.kind == "bone"]
        bone = present & np.isin(labels, bone_ids)
        if bone.any():
            scene.add_mesh("bone", structure_polydata(bone, origin, h, 10), BONE_RGB,
                           opacity=BONE_OPACITY)
        top = vtkRenderer()                       # the regions over everything
        top.SetLayer(1)
        top.SetActiveCamera(scene.renderer.GetActiveCamera())
        top.InteractiveOff()
        scene.render_window.AddRenderer(top)
        fs = legend_font_px(size[1])
        lines = [(title, (1.0, 1.0, 1.0), fs + 2)]
        for n, it in enumerate(items, start=1):
            rgb = np.array(OUTCOME_RGB.get(it.outcome, OUTCOME_RGB["n/a"])) / 255.0
            score = "n/a" if it.score is None else f"{it.score}/2"
            word = "" if it.outcome in ("done", "partial", "n/a") else f" {it.outcome}"
            lines.append((f"{n:2d}  [{score}]{word}  {it.title}", rgb, fs))
            reg = np.asarray(it.region_mm, float).reshape(-1, 3)
            if it.score is None:
                continue
            if len(reg):
                top.AddActor(cubes_actor(reg, CUBE_FILL * h, np.asarray(
                    OUTCOME_RGB[it.outcome]), REGION_OPACITY))
            if it.anchor_mm is not None:
                t = vtkBillboardTextActor3D()
                t.SetInput(str(n))
                t.SetPosition(*map(float, it.anchor_mm))
                tp = t.GetTextProperty()
                tp.SetFontSize(fs + 2)
                tp.SetBold(True)
                tp.SetColor(*rgb)
                tp.SetBackgroundColor(0.0, 0.0, 0.0)
                tp.SetBackgroundOpacity(0.6)
                top.AddActor(t)
        lines += [("green: done   amber: partial   red: missed or violated",
                   (0.92, 0.92, 0.88), fs)]
        lines += [(clinical_name(st.name), np.array(st.display_color[:3]) / 255.0, fs)
                  for st in drawn]
        add_legend(top, lines, size[1] - 8)   # over the regions, which lie in the top layer
        eye, focal, up = (np.asarray(v, float) for v in camera)
        scene.set_case_camera(focal + (eye - focal) / ZOOM, focal, up)
        return scene.screenshot(path)
    finally:
        scene.close()
