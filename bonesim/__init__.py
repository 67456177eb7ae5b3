"""bonesim: a temporal-bone drilling simulator.

The core contract (see :mod:`bonesim.engine.model`; files: :mod:`bonesim.io.loading`)::

    import bonesim
    model = bonesim.load_model("phantom", "cutting-5mm")   # immutable
    state = bonesim.make_state(model)                      # mutable
    force = bonesim.world_step(model, state, sample)       # one step of the world
    force = bonesim.step(model, state, sample)             # the haptic step alone
    replica = bonesim.TissueReplica(model, state)          # a consumer's copy

``import bonesim`` is light: it imports no rendering, sound or device
library, and loads the engine modules only when first used.
"""
from __future__ import annotations

#: The package version, written into every session file's header and every
#: JSON output of the command line. It changes whenever the bundled data (a
#: case, burr or material: a new kept version such as ``phantom@1``) or the
#: session schema changes, so that files and outputs tell the versions apart.
#: pyproject.toml reads it from here.
__version__ = "0.2.0"

_LAZY = {
    "Model": "bonesim.engine.model",
    "State": "bonesim.engine.model",
    "Sample": "bonesim.engine.model",
    "load_model": "bonesim.io.loading",
    "make_model": "bonesim.engine.model",
    "make_state": "bonesim.engine.model",
    "step": "bonesim.engine.model",
    "world_step": "bonesim.engine.world",
    "warmup": "bonesim.io.loading",
    "Grid": "bonesim.engine.grid",
    "BonesimError": "bonesim.errors",
    "DeviceCaps": "bonesim.engine.device_caps",
    "data_path": "bonesim.resources",
    "TissueReplica": "bonesim.engine.replica",
    "read_session": "bonesim.session.reader",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        mod = importlib.import_module(_LAZY[name])
        return getattr(mod, name)
    raise AttributeError(f"module 'bonesim' has no attribute {name!r}")
