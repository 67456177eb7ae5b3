"""Rendering: the VTK scene, the interactive window and offscreen frames.

This is the only part of bonesim that imports VTK (``import bonesim`` never
imports it). The submodules:

:mod:`~bonesim.render.gl`
    Chooses a working OpenGL path (X11, EGL or OSMesa) without a display.
:mod:`~bonesim.render.scene`
    :class:`Scene`: bone surface, critical structures, tool, dust, HUD,
    microscope camera, visible subset, screenshots.
:mod:`~bonesim.render.window`
    :class:`Window`: the interactive (or offscreen) frame loop, keys and mouse.
:mod:`~bonesim.render.bench`
    :func:`bench_render` figures.

Names are loaded lazily, so ``import bonesim.render`` alone stays cheap.
"""
from __future__ import annotations

_LAZY = {
    "Scene": "scene", "Window": "window", "DEFAULT_KEYS": "window",
    "select_backend": "gl", "start_probe": "gl", "GLInfo": "gl",
    "RenderUnavailable": "gl", "bench_render": "bench",
    "compare_images": "imagecmp", "read_png": "imagecmp", "write_png": "imagecmp",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        mod = importlib.import_module(f".{_LAZY[name]}", __name__)
        return getattr(mod, name)
    raise AttributeError(f"module 'bonesim.render' has no attribute {name!r}")
