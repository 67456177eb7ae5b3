"""Pick an OpenGL path for VTK that works on this machine, display or not.

VTK's Linux wheels (9.4 and later) carry three OpenGL render-window classes
and choose one when a window is created, from the environment variable
``VTK_DEFAULT_OPENGL_WINDOW``:

``x11``
    ``vtkXOpenGLRenderWindow``: a GLX window on the X server named by
    ``DISPLAY`` (a desktop, or Xvfb on a headless machine). The only path
    for an interactive window.
``egl``
    ``vtkEGLRenderWindow``: offscreen through ``libEGL``. With Mesa and no
    GPU this is the *llvmpipe* software rasterizer behind Mesa's
    software/surfaceless EGL device; with a GPU and its EGL driver, the GPU.
``osmesa``
    ``vtkOSOpenGLRenderWindow``: offscreen through ``libOSMesa`` (Mesa's
    off-screen library, llvmpipe as well).

A broken path can abort the process inside a C library (a missing
``libOSMesa`` or a dead X connection), so every candidate is first tried in
a child Python process that renders one small frame and reads a pixel back.
The first candidate that works is recorded in ``VTK_DEFAULT_OPENGL_WINDOW``
and used for every window this process creates.

Order tried: offscreen ``egl``, ``osmesa``, then ``x11`` (if ``DISPLAY`` is
set); onscreen ``x11`` only.

Environment
-----------
``BONESIM_GL``
    Comma-separated candidates to try instead of the default order
    (e.g. ``osmesa`` or ``egl,x11``).
``BONESIM_GL_PROBE=0``
    Trust the first candidate without the child-process check (saves the
    child's start-up, ~0.5 s; use only where that path is known to work).

Software-GL settings: nothing else is set. Mesa picks llvmpipe when no GPU
driver matches; ``LP_NUM_THREADS`` (default: one per core) bounds its
rasterizer threads, ``VTK_DEFAULT_EGL_DEVICE_INDEX`` picks the EGL device
when there are several.

Debian packages: ``libegl1 libegl-mesa0 libgl1-mesa-dri`` (EGL + llvmpipe),
``libosmesa6`` (OSMesa), ``libgl1 libglx-mesa0 libx11-6 libxcursor1`` and
``xvfb xauth`` (X/GLX, and a virtual X server for headless interactive use).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from dataclasses import dataclass, field

from bonesim.errors import BonesimError

__all__ = ["WINDOW_CLASS", "OFFSCREEN_ORDER", "ONSCREEN_ORDER", "PROBE_TIMEOUT_S",
           "RenderUnavailable", "GLInfo", "probe", "candidates", "start_probe",
           "select_backend", "make_render_window", "reset"]

#: Render-window class of each backend.
WINDOW_CLASS = {
    "x11": "vtkXOpenGLRenderWindow",
    "egl": "vtkEGLRenderWindow",
    "osmesa": "vtkOSOpenGLRenderWindow",
}
#: Backends that need no display.
OFFSCREEN_ORDER = ("egl", "osmesa", "x11")
ONSCREEN_ORDER = ("x11",)
#: Seconds a probe may take before it counts as failed.
PROBE_TIMEOUT_S = 60.0

_HINT = ("install Mesa's software OpenGL (Debian: apt-get install libegl1 libegl-mesa0 "
         "libgl1-mesa-dri, or libosmesa6), or run under a virtual X server "
         "(apt-get install xvfb xauth; xvfb-run -a ...)")

# The child: one 64x64 frame with a red square on black, centre pixel read back.
_PROBE = r"""
import json, sys
offscreen = sys.argv[1] == "1"
import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (registers the GL classes)
from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
from vtkmodules.vtkFiltersSources import vtkPlaneSource
from vtkmodules.vtkRenderingCore import (vtkActor, vtkPolyDataMapper, vtkRenderer,
                                         vtkRenderWindow)
rw = vtkRenderWindow()
rw.SetOffScreenRendering(1 if offscreen else 0)
rw.SetSize(64, 64)
ren = vtkRenderer()
ren.SetBackground(0, 0, 0)
rw.AddRenderer(ren)
src = vtkPlaneSource()
m = vtkPolyDataMapper()
m.SetInputConnection(src.GetOutputPort())
a = vtkActor()
a.SetMapper(m)
a.GetProperty().SetColor(1, 0, 0)
a.GetProperty().LightingOff()
ren.AddActor(a)
ren.ResetCamera()
rw.Render()
px = vtkUnsignedCharArray()
rw.GetPixelData(32, 32, 32, 32, 0 if offscreen else 1, px, 0)
rgb = [px.GetValue(i) for i in range(3)]
cap = rw.ReportCapabilities() or ""
info = {"window": rw.GetClassName(), "rgb": rgb}
for line in cap.splitlines():
    if "renderer string" in line:
        info["renderer"] = line.split(":", 1)[1].strip()
    elif "version string" in line and "OpenGL" in line:
        info["version"] = line.split(":", 1)[1].strip()
rw.Finalize()
print("BONESIM_GL_PROBE " + json.dumps(info))
sys.stdout.flush()
"""


class RenderUnavailable(BonesimError):
    """No OpenGL path works here; the message lists every attempt and a fix."""


@dataclass(frozen=True)
class GLInfo:
    """The OpenGL path chosen.

    Attributes
    ----------
    backend : str
        ``"x11"``, ``"egl"`` or ``"osmesa"``.
    window_class : str
        VTK render-window class.
    renderer : str
        ``GL_RENDERER`` (e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)``), ``""``
        when not probed.
    version : str
        ``GL_VERSION``.
    software : bool
        True for a CPU rasterizer (llvmpipe, softpipe, swrast).
    env : dict
        Environment variables set for it.
    """

    backend: str
    window_class: str
    renderer: str = ""
    version: str = ""
    software: bool = False
    env: dict = field(default_factory=dict)

    def describe(self) -> str:
        what = self.renderer or "not probed"
        return f"{self.backend} ({self.window_class}; {what})"


def probe(backend: str, offscreen: bool = True, timeout_s: float = PROBE_TIMEOUT_S):
    """Try ``backend`` in a child process.

    Parameters
    ----------
    backend : {"x11", "egl", "osmesa"}
    offscreen : bool
        Render to an offscreen buffer (False: a mapped window; x11 only).
    timeout_s : float
        Give up after this long [s].

    Returns
    -------
    GLInfo or str
        The working path, or why it failed (one line).
    """
    proc = _start_probe(backend, offscreen)
    if isinstance(proc, str):
        return proc
    return _finish_probe(backend, proc, timeout_s)


def _start_probe(backend: str, offscreen: bool):
    if backend not in WINDOW_CLASS:
        return f"unknown backend {backend!r}"
    if backend == "x11" and not os.environ.get("DISPLAY"):
        return "DISPLAY is not set (no X server)"
    env = dict(os.environ)
    env["VTK_DEFAULT_OPENGL_WINDOW"] = WINDOW_CLASS[backend]
    try:
        return subprocess.Popen([sys.executable, "-c", _PROBE, "1" if offscreen else "0"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env, stdin=subprocess.DEVNULL)
    except OSError as exc:          # pragma: no cover - no python?
        return f"cannot start a probe process: {exc}"


def _finish_probe(backend: str, proc, timeout_s: float):
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return f"no frame within {timeout_s:.0f} s"
    info = None
    for line in out.splitlines():
        if line.startswith("BONESIM_GL_PROBE "):
            info = json.loads(line.split(" ", 1)[1])
    if info is None:
        return _failure_line(proc.returncode, err)
    want = WINDOW_CLASS[backend]
    if info.get("window") != want:
        return f"VTK made a {info.get('window')} instead of {want}"
    r, g, b = info.get("rgb", [0, 0, 0])
    if not (r > 128 and g < 64 and b < 64):
        return f"rendered frame is wrong (centre pixel {r, g, b}, expected red)"
    renderer = info.get("renderer", "")
    soft = any(s in renderer.lower() for s in ("llvmpipe", "softpipe", "swrast"))
    return GLInfo(backend, want, renderer, info.get("version", ""), soft,
                  {"VTK_DEFAULT_OPENGL_WINDOW": want})


def _failure_line(code, err: str) -> str:
    lines = [ln.strip() for ln in (err or "").splitlines() if ln.strip()]
    keep = [ln for ln in lines if any(w in ln.lower() for w in
                                      ("error", "warn", "not found", "cannot", "fail"))]
    msg = (keep or lines or ["no output"])[-1]
    if "|" in msg:                      # strip VTK's log prefix
        msg = msg.split("|", 1)[1].strip()
    msg = msg.replace("\x1b[0m", "").replace("\x1b[33m", "").replace("\x1b[31m", "")
    return f"exit status {code}: {msg[:200]}"


def candidates(offscreen: bool = True) -> list[str]:
    """Backends to try, in order (``BONESIM_GL`` overrides the default)."""
    env = os.environ.get("BONESIM_GL", "").strip()
    if env and env != "auto":
        names = [s.strip().lower() for s in env.split(",") if s.strip()]
        bad = [n for n in names if n not in WINDOW_CLASS]
        if bad:
            raise RenderUnavailable(f"BONESIM_GL names unknown backend(s) {bad}; "
                                    f"known: {sorted(WINDOW_CLASS)}")
        if not offscreen:
            names = [n for n in names if n == "x11"] or ["x11"]
        return names
    return list(OFFSCREEN_ORDER if offscreen else ONSCREEN_ORDER)


_lock = threading.Lock()
_chosen: dict = {}          # offscreen flag -> GLInfo
_pending: dict = {}         # offscreen flag -> {backend: Popen | str}


def start_probe(offscreen: bool = True) -> None:
    """Start probing the first candidate in a child process, without waiting.

    Call early (before loading a case) so the probe overlaps with other
    start-up work; :func:`select_backend` collects the result (and tries the
    other candidates one by one if it failed).
    """
    with _lock:
        if offscreen in _chosen or offscreen in _pending:
            return
        if os.environ.get("BONESIM_GL_PROBE", "1") == "0":
            return
        first = candidates(offscreen)[0]
        _pending[offscreen] = {first: _start_probe(first, offscreen)}


def select_backend(offscreen: bool = True) -> GLInfo:
    """The OpenGL path for this process's render windows (probed once).

    Sets ``VTK_DEFAULT_OPENGL_WINDOW`` accordingly.

    Parameters
    ----------
    offscreen : bool
        Whether the windows render offscreen (no display needed) or must
        be shown on an X display.

    Raises
    ------
    RenderUnavailable
        If no candidate works; the message says what each attempt gave and
        which packages to install.
    """
    with _lock:
        if offscreen in _chosen:
            info = _chosen[offscreen]
        else:
            names = candidates(offscreen)
            if os.environ.get("BONESIM_GL_PROBE", "1") == "0":
                b = names[0]
                if b == "x11" and not os.environ.get("DISPLAY"):
                    raise RenderUnavailable("BONESIM_GL_PROBE=0 with backend x11 but "
                                            "DISPLAY is not set; " + _HINT)
                info = GLInfo(b, WINDOW_CLASS[b], env={"VTK_DEFAULT_OPENGL_WINDOW":
                                                       WINDOW_CLASS[b]})
            else:
                procs = _pending.pop(offscreen, None) or {}
                failures = []
                info = None
                for b in names:
                    proc = procs.pop(b, None)
                    if proc is None:
                        proc = _start_probe(b, offscreen)
                    res = proc if isinstance(proc, str) else _finish_probe(
                        b, proc, PROBE_TIMEOUT_S)
                    if isinstance(res, GLInfo):
                        info = res
                        break
                    failures.append(f"{b}: {res}")
                for proc in procs.values():          # probes no longer needed
                    if not isinstance(proc, str):
                        proc.kill()
                        proc.communicate()
                if info is None:
                    mode = "offscreen" if offscreen else "onscreen (interactive)"
                    raise RenderUnavailable(
                        f"no working OpenGL path for {mode} rendering ("
                        + "; ".join(failures) + "); " + _HINT)
            _chosen[offscreen] = info
    os.environ.update(info.env)
    return info


def make_render_window(offscreen: bool = True, size=(800, 600)):
    """A VTK render window on the selected OpenGL path.

    Parameters
    ----------
    offscreen : bool
        No display needed (True) or an interactive X window (False).
    size : (2,) int
        Width, height [pixels].

    Returns
    -------
    window : vtkRenderWindow
    info : GLInfo
    """
    info = select_backend(offscreen)
    import vtkmodules.vtkRenderingOpenGL2  # noqa: F401
    from vtkmodules.vtkRenderingCore import vtkRenderWindow

    os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = info.window_class
    rw = vtkRenderWindow()
    if rw.GetClassName() != info.window_class:
        raise RenderUnavailable(f"VTK created a {rw.GetClassName()} although "
                                f"{info.window_class} was requested; " + _HINT)
    rw.SetOffScreenRendering(1 if offscreen else 0)
    rw.SetSize(int(size[0]), int(size[1]))
    return rw, info


def reset() -> None:
    """Forget the chosen paths (tests)."""
    with _lock:
        _chosen.clear()
        for procs in _pending.values():
            for p in procs.values():
                if not isinstance(p, str):
                    p.kill()
                    p.communicate()
        _pending.clear()
