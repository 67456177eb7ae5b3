"""OpenGL path selection: probing in a child process, clear failures."""
from __future__ import annotations

import pytest

from bonesim.render import gl


def test_offscreen_backend_renders(gl_info):
    assert gl_info.backend in ("egl", "osmesa", "x11")
    assert gl_info.window_class == gl.WINDOW_CLASS[gl_info.backend]
    assert gl_info.renderer            # probed: GL_RENDERER reported


def test_make_render_window_uses_the_chosen_class(gl_info):
    rw, info = gl.make_render_window(True, (64, 48))
    try:
        assert rw.GetClassName() == info.window_class
        assert tuple(rw.GetSize()) == (64, 48)
    finally:
        rw.Finalize()


def test_probe_reports_a_missing_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    res = gl.probe("x11")
    assert isinstance(res, str) and "DISPLAY" in res


def test_probe_rejects_unknown_backend():
    assert "unknown backend" in gl.probe("metal")


def test_no_working_path_is_one_clear_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("BONESIM_GL", "x11")
    saved = dict(gl._chosen)
    gl._chosen.clear()
    try:
        with pytest.raises(gl.RenderUnavailable) as exc:
            gl.select_backend(offscreen=True)
    finally:
        gl._chosen.clear()
        gl._chosen.update(saved)
    msg = str(exc.value)
    assert "x11: DISPLAY is not set" in msg
    assert "libegl-mesa0" in msg and "xvfb" in msg


def test_candidates_from_environment(monkeypatch):
    monkeypatch.setenv("BONESIM_GL", "osmesa, egl")
    assert gl.candidates(True) == ["osmesa", "egl"]
    assert gl.candidates(False) == ["x11"]
    monkeypatch.setenv("BONESIM_GL", "vulkan")
    with pytest.raises(gl.RenderUnavailable, match="unknown backend"):
        gl.candidates(True)
    monkeypatch.delenv("BONESIM_GL")
    assert gl.candidates(True) == list(gl.OFFSCREEN_ORDER)


def test_import_bonesim_does_not_import_vtk():
    import subprocess
    import sys

    code = ("import sys, bonesim; bonesim.load_model; import bonesim.render; "
            "bad = [m for m in sys.modules if m.startswith(('vtk', 'pyvista'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
