"""bonesim: a temporal-bone drilling simulator.

The core contract (see :mod:`bonesim.model`; files: :mod:`bonesim.loading`)::

    import bonesim
    model = bonesim.load_model("phantom", "cutting-5mm")   # immutable
    state = bonesim.make_state(model)                      # mutable
    force = bonesim.step(model, state, sample)             # one haptic step
    replica = bonesim.TissueReplica(model, state)          # a consumer's copy

``import bonesim`` is light: it imports no rendering, sound or device
library, and loads the engine modules only when first used.
"""
from __future__ import annotations

__version__ = "0.1.0"

_LAZY = {
    "Model": "model", "State": "model", "Sample": "model", "load_model": "loading",
    "make_model": "model", "make_state": "model", "step": "model", "warmup": "loading",
    "Grid": "grid", "BonesimError": "errors", "DeviceCaps": "device_caps",
    "data_path": "resources", "TissueReplica": "replica", "read_session": "session_reader",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        mod = importlib.import_module(f".{_LAZY[name]}", __name__)
        return getattr(mod, name)
    raise AttributeError(f"module 'bonesim' has no attribute {name!r}")
