"""Rendering: the VTK scene, the interactive window and offscreen frames.

This is the only part of bonesim that imports VTK (``import bonesim`` never
imports it). The submodules:

:mod:`~bonesim.render.gl`
    Chooses a working OpenGL path (X11, EGL or OSMesa) without a display.
:mod:`~bonesim.render.scene`
    :class:`Scene`: bone surface, critical structures, tool (and its
    silhouette when bone hides it), dust, HUD, microscope camera and lights,
    stereo, visible subset, screenshots.
:mod:`~bonesim.render.layout`
    The side panel beside the 3D view (HUD, hint, monitor trace), lights,
    stereo switching (part of :class:`Scene`).
:mod:`~bonesim.render.dustview`, :mod:`~bonesim.render.stereo`,
:mod:`~bonesim.render.geometry`, :mod:`~bonesim.render.style`
    Dust sprites, stereo modes, tool and structure geometry, and the look
    read from ``bonesim/data/render.toml``.
:mod:`~bonesim.render.window`
    :class:`Window`: the interactive (or offscreen) frame loop, keys and mouse.
:mod:`~bonesim.render.bench`
    :func:`bench_render` figures.

Names are loaded lazily, so ``import bonesim.render`` alone stays cheap.

Driving it from the app (sketch; the haptic loop and devices are the app's)::

    from bonesim.render import gl
    gl.start_probe(offscreen=False)            # overlap the GL probe with loading
    from bonesim.render.scene import Scene
    from bonesim.render.window import Window

    scene = Scene.from_model(model, consumer.surface, offscreen=False)

    def on_frame(scene):                       # main thread, once per frame
        ch = consumer.drain()                  # TissueReplica: events -> Surface.update
        scene.update_bodies(consumer, ch.changed, ch.touched)   # each body at its pose
        depth = depth_below_surface_mm(grid, pos_mm, scene.camera_pose()[0],
                                       model.burr.radius_mm)     # bonesim.physics.sightline
        scene.set_tool(pos_mm, axis, model.burr.radius_mm, drill_on, depth_mm=depth)
        scene.set_dust(*dust.sprites())            # bonesim.physics.dust.DustGrid
        scene.set_hud({"case": model.name, "burr": model.burr.name,
                       "burr_kind": model.burr.kind,
                       "burr_diameter_mm": model.burr.diameter_mm,
                       "drill": drill_on, "direction": direction,
                       "speed_rpm": rpm, "force_n": f, "depth_mm": depth,
                       "haptic_hz": rate,
                       "elapsed_s": t, "injuries": names})

    def on_key(action): ...                    # "next_burr", "drill_toggle", ...
    def on_mouse(world_mm, buttons): ...       # target point on the tool's view plane

    Window(scene, on_frame, on_key, on_mouse, frame_hz=60).run()

Stereo: ``scene.set_stereo("side-by-side")`` (or ``"anaglyph"``,
``"interlaced"``, ``"checkerboard"``, ``"quad-buffer"`` on a display with a
stereo context, made with ``Scene(..., stereo_capable=True)``).

For headless runs make the scene with ``offscreen=True`` and call
``Window(...).run_offscreen(n_frames, screenshot="last.png")``.

Threads: every call into a :class:`Scene` and every ``Surface.update`` of
the drawn surface must happen on the thread that made the scene (VTK is not
thread-safe); the scene's own background work (the visible subset) only
reads private copies.
"""
from __future__ import annotations

_LAZY = {
    "Scene": "scene", "Window": "window", "DEFAULT_KEYS": "window",
    "select_backend": "gl", "start_probe": "gl", "GLInfo": "gl",
    "RenderUnavailable": "gl", "bench_render": "bench",
    "compare_images": "imagecmp", "read_png": "imagecmp", "write_png": "imagecmp",
    "STEREO_MODES": "stereo", "StereoUnavailable": "stereo", "bench_fps": "bench",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        mod = importlib.import_module(f".{_LAZY[name]}", __name__)
        return getattr(mod, name)
    raise AttributeError(f"module 'bonesim.render' has no attribute {name!r}")
