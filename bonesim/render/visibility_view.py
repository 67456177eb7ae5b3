"""The voxel-visibility view: a run's removals coloured by whether the eye saw them.

After the thesis's figure of voxel visibility (SPEC "Voxel visibility"): the
removed voxels are small cubes at their case-frame centres, green when the
voxel was visible at its removal and red when it was hidden (undercut); the
bone is not drawn, the chosen structures are. :func:`visibility_scene` builds
the view from plain arrays (the research metrics compute them:
:func:`metrics.visibility.visibility`); :func:`show_visibility` opens it in a
window to turn about with the mouse, or runs it offscreen for a picture.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bonesim.io.anatomy import clinical_name
from bonesim.render.hud import format_help

__all__ = ["VISIBLE_RGB", "HIDDEN_RGB", "VISIBLE_OPACITY", "CUBE_FILL", "VIEWER_KEYS",
           "VIEWER_MOUSE_HELP", "legend_font_px", "add_legend", "visibility_scene",
           "viewer_window",
           "show_visibility"]

#: Colour of removals that were visible (0-255 RGB).
VISIBLE_RGB = (40, 200, 60)
#: Colour of removals that were hidden (0-255 RGB).
HIDDEN_RGB = (230, 40, 30)
#: Opacity of the visible removals' cubes: the hidden ones, usually deeper,
#: show through them.
VISIBLE_OPACITY = 0.3
#: A removal's cube edge as a share of the voxel edge (gaps keep cubes apart).
CUBE_FILL = 0.9
#: Keys of the viewer: VTK key symbol -> window action.
VIEWER_KEYS = {"c": "screenshot", "F12": "screenshot", "h": "help", "F1": "help",
               "v": "reset_view", "Home": "reset_view", "q": "quit", "Escape": "quit"}
#: The viewer's mouse, for the help overlay.
VIEWER_MOUSE_HELP = (
    "left / right drag    orbit",
    "Shift+left, middle   pan",
    "wheel, Ctrl+right    zoom",
)


def legend_font_px(height_px: int) -> int:
    """Legend font size [px] for an image ``height_px`` tall."""
    return max(10, int(round(height_px / 48)))


def visibility_scene(model, centre_mm, visible, chosen, title: str, lines, *,
                     size=(1024, 768), offscreen: bool = True, view=None):
    """Build the visibility view.

    Parameters
    ----------
    model : bonesim.engine.model.Model
        The run's case (structures, grid, camera).
    centre_mm : (n, 3) float
        Removed voxels' centres, case frame [mm].
    visible : (n,) int
        1 visible at removal, anything else hidden.
    chosen : sequence of str
        Structures to draw (by name; the colour key shows their clinical
        names).
    title : str
    lines : sequence of str
        Legend lines under the title (fractions); the colour key and the
        chosen structures' colours follow them.
    size : (int, int)
        Width, height [px].
    offscreen : bool
        Render without a display.
    view : (eye_mm, focal_mm, up), optional
        Camera, case frame [mm] (default: the case camera, else fitted).

    Returns
    -------
    bonesim.render.scene.Scene
        Close it when done.
    """
    from bonesim.render.scene import Scene

    centre_mm = np.asarray(centre_mm, np.float64).reshape(-1, 3)
    visible = np.asarray(visible).reshape(-1)
    if len(visible) != len(centre_mm):
        raise ValueError(f"visible has {len(visible)} entries, centre_mm {len(centre_mm)}")
    scene = Scene(size=size, offscreen=offscreen, visible_subset=False, panel=False)
    try:
        scene.set_hint("")
        scene.voxel_mm = float(model.spacing_mm)
        sts = [st if st.name in chosen else
               SimpleNamespace(name=st.name, kind="_hidden", display_color=(0, 0, 0))
               for st in model.structures]
        scene.add_structures(model.grid, sts, skip_kinds=("_hidden",))
        e = CUBE_FILL * float(model.spacing_mm)
        for sel, rgb, opacity in ((visible == 1, VISIBLE_RGB, VISIBLE_OPACITY),
                                  (visible != 1, HIDDEN_RGB, 1.0)):
            if sel.any():
                scene.renderer.AddActor(cubes_actor(centre_mm[sel], e, rgb, opacity))
        cam = getattr(getattr(model, "case", None), "camera", None)
        if view is not None:
            scene.set_camera(*view)
        elif cam is not None:
            scene.set_case_camera(cam.eye_mm, cam.focal_mm, cam.up)
        else:
            scene.fit_camera()
        scene.set_case_camera(*scene.camera_pose())     # "v" comes back to this view
        fs = legend_font_px(size[1])
        y = size[1] - 8
        texts = [(title, (1.0, 1.0, 1.0), fs + 2)] + \
            [(ln, (0.92, 0.92, 0.88), fs) for ln in lines] + \
            [("green: visible when removed", np.array(VISIBLE_RGB) / 255, fs),
             ("red: hidden when removed (undercut)", np.array(HIDDEN_RGB) / 255, fs)] + \
            [(clinical_name(st.name), np.array(st.display_color[:3]) / 255, fs)
             for st in model.structures if st.name in chosen]
        add_legend(scene.renderer, texts, y)
    except BaseException:
        scene.close()
        raise
    return scene


def add_legend(renderer, lines, top_px: int) -> None:
    """Lines of text down the top-left corner of ``renderer``'s view.

    Parameters
    ----------
    renderer : vtkRenderer
    lines : sequence of (str, (3,) float 0-1, int)
        Text, colour and font size [px] of each line.
    top_px : int
        Where the first line's top sits [px from the bottom].
    """
    import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text rendering)
    from vtkmodules.vtkRenderingCore import vtkTextActor

    y = top_px
    for text, rgb, s in lines:
        a = vtkTextActor()
        a.SetInput(text)
        tp = a.GetTextProperty()
        tp.SetFontSize(s)
        tp.SetColor(*map(float, rgb))
        tp.SetVerticalJustificationToTop()
        tp.SetBackgroundColor(0.0, 0.0, 0.0)
        tp.SetBackgroundOpacity(0.45)
        a.SetDisplayPosition(10, y)
        a.PickableOff()
        renderer.AddViewProp(a)
        y -= int(s * 1.35)


def viewer_window(scene):
    """A :class:`~bonesim.render.window.Window` around ``scene`` that drives no
    tool: the mouse turns, pans and zooms the view (:data:`VIEWER_MOUSE_HELP`),
    the keys are :data:`VIEWER_KEYS`."""
    from bonesim.render.window import Window

    win = Window(scene, None, keys=VIEWER_KEYS, frame_hz=30.0)
    scene.set_help(format_help(VIEWER_KEYS, VIEWER_MOUSE_HELP))
    return win


def show_visibility(scene, frames: int | None = None, screenshot=None) -> dict:
    """Show a :func:`visibility_scene` in a window: the mouse turns, pans and
    zooms it (:data:`VIEWER_MOUSE_HELP`), ``c`` saves a picture, ``v`` goes
    back to the case camera, ``q`` closes it.

    Parameters
    ----------
    scene : Scene
    frames : int, optional
        Stop after this many frames (offscreen: default 1).
    screenshot : path, optional
        Save the last frame.

    Returns
    -------
    dict
        The window's summary (frames, rate, ``screenshot``).
    """
    win = viewer_window(scene)
    if scene.offscreen:
        return win.run_offscreen(frames or 1, screenshot=screenshot)
    out = win.run(max_frames=frames)
    if screenshot is not None:
        out["screenshot"] = str(scene.screenshot(screenshot))
    return out


def cubes_actor(centre_mm, edge_mm, rgb, opacity):
    """One actor of cubes of edge ``edge_mm`` at ``centre_mm`` (n, 3) [mm]."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkPolyData
    from vtkmodules.vtkFiltersSources import vtkCubeSource
    from vtkmodules.vtkRenderingCore import vtkActor, vtkGlyph3DMapper

    pts = vtkPoints()
    pts.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(centre_mm, np.float32),
                                           deep=True))
    pd = vtkPolyData()
    pd.SetPoints(pts)
    cube = vtkCubeSource()
    cube.SetXLength(edge_mm)
    cube.SetYLength(edge_mm)
    cube.SetZLength(edge_mm)
    gm = vtkGlyph3DMapper()
    gm.SetInputData(pd)
    gm.SetSourceConnection(cube.GetOutputPort())
    gm.ScalingOff()
    gm.OrientOff()
    gm.ScalarVisibilityOff()
    a = vtkActor()
    a.SetMapper(gm)
    p = a.GetProperty()
    p.SetColor(*(np.asarray(rgb, float) / 255.0))
    p.SetOpacity(float(opacity))
    p.SetAmbient(0.35)
    p.SetDiffuse(0.75)
    return a
