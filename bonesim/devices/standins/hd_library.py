"""Build and load ``hd_stub.c``, a stub of the OpenHaptics HD library's C
functions over a simulated Touch-class arm, as ``libHD.so``.

Loaded first under its soname (``RTLD_GLOBAL``), it is what the
pyopenhaptics binding's ``CDLL("libHD.so")`` then finds, so the binding's
real Python code runs over it. Test controls: ``stub_place(x, y, z)`` puts
the hand holding the stylus at rest there [mm], ``stub_unplug(1/0)``,
``stub_rendered(double[3])`` (the force the arm renders [N]),
``stub_position(double[3])``, ``stub_frames()``, ``stub_running()``.
"""
from __future__ import annotations

import atexit
import ctypes
import shutil
import subprocess
import tempfile
from pathlib import Path

from bonesim.errors import BonesimError

__all__ = ["SOURCE", "build", "load"]

#: The stub's C source.
SOURCE = Path(__file__).with_name("hd_stub.c")


def build(folder) -> Path:
    """Compile the stub into ``folder/libHD.so`` (soname ``libHD.so``)."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        raise BonesimError("building the HD library stub needs a C compiler (apt-get install "
                           "gcc)")
    out = Path(folder) / "libHD.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-Wl,-soname,libHD.so", "-o", str(out),
                    str(SOURCE), "-lpthread", "-lm"], check=True, capture_output=True)
    return out


#: The stub this process loaded (:func:`load`).
_LOADED = None


def load():
    """Build the stub and load it globally, once per process; returns the
    ``ctypes.CDLL`` with the test controls' signatures set, its arm put back
    (plugged in, no buttons, at the origin). ``Path(lib._name).parent`` is
    the folder holding ``libHD.so`` (put it on ``LD_LIBRARY_PATH`` for a
    child process), kept until this process exits.

    Once per process because the binding opens ``libHD.so`` by name and
    keeps the first one loaded: a second copy from another folder would be
    a second arm the binding never reads.
    """
    global _LOADED
    if _LOADED is None:
        folder = tempfile.mkdtemp(prefix="bonesim-hd-")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        lib = ctypes.CDLL(str(build(folder)), mode=ctypes.RTLD_GLOBAL)
        lib.stub_place.argtypes = [ctypes.c_double] * 3
        lib.stub_unplug.argtypes = [ctypes.c_int]
        lib.stub_set_buttons.argtypes = [ctypes.c_int]
        lib.stub_rendered.argtypes = [ctypes.POINTER(ctypes.c_double)]
        lib.stub_position.argtypes = [ctypes.POINTER(ctypes.c_double)]
        lib.stub_frames.restype = ctypes.c_long
        _LOADED = lib
    lib = _LOADED
    lib.stub_unplug(0)
    lib.stub_set_buttons(0)
    lib.stub_place(0.0, 0.0, 0.0)
    return lib
