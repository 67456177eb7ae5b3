"""Child process of the Xvfb test: the interactive window's timer-driven
loop on a real X server, with a scripted frame callback that drills.

Usage: ``python -m tests.bonesim.render.xloop OUT.json`` with ``DISPLAY`` set.
"""
from __future__ import annotations

import json
import sys

import numpy as np


def main(out_path: str, n_frames: int = 40) -> None:
    from bonesim.engine.grid import voxel_offset
    from bonesim.render.scene import Scene
    from bonesim.render.window import Window
    from bonesim.engine.surface import Surface
    from tests.bonesim.render.scenes import nerve_block

    model, state = nerve_block()
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    scene = Scene.from_model(model, surf, size=(320, 240), offscreen=False)
    scene.set_case_camera((8.0, -20.0, 40.0), (8.0, 8.0, 4.0), (0.0, 0.0, 1.0))
    rec = {"keys": [], "mouse": 0, "triangles": [surf.n_triangles], "hud": []}

    def on_frame(sc):
        f = win.frames
        # drill one 4x4 voxel column a layer deeper each frame, from the top
        k = 15 - (f % 16)
        ijk = np.array([(i, j, k) for i in range(14, 18) for j in range(4, 8)], np.int32)
        for i, j, kk in ijk:
            grid.density[grid.brick_index(i, j, kk), voxel_offset(i, j, kk)] = 0.0
        surf.update(grid, ijk)
        sc.update_surface(surf)
        sc.set_tool(((16.0) * 0.5, 6.0 * 0.5, (k + 1.5) * 0.5), (0, 0, -1), 1.0, True)
        sc.set_hud({"case": "block", "haptic_hz": 1000.0, "drill": True,
                    "elapsed_s": f / 60.0})
        rec["triangles"].append(surf.n_triangles)
        rec["hud"].append(sc.hud_text)
        if f == 5:                       # a key and a mouse move through the interactor
            iren = win.interactor
            iren.SetEventInformation(160, 120, 0, 0, "\0", 0, "space")
            iren.InvokeEvent("KeyPressEvent")
            iren.SetEventInformation(170, 120, 0, 0, "\0", 0, None)
            iren.InvokeEvent("MouseMoveEvent")

    def on_key(action):
        rec["keys"].append(action)

    def on_mouse(p, buttons):
        rec["mouse"] += 1

    win = Window(scene, on_frame, on_key, on_mouse, frame_hz=60.0)
    summary = win.run(max_frames=n_frames)
    out = {"summary": summary, "window": scene.render_window.GetClassName(),
           "mapped": bool(scene.render_window.GetMapped()),
           "offscreen": bool(scene.render_window.GetOffScreenRendering()),
           "frame_hz": scene.frame_hz, "final_hud": scene.hud_text, **rec}
    scene.close()
    with open(out_path, "w") as fh:
        json.dump(out, fh)


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:]))
