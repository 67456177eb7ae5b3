"""What the command line prints as JSON, stamped with the package version.

Every ``--json`` output of ``bonesim`` (``bonesim metrics`` included) goes
through :func:`print_json`, so that a saved output says which bonesim made
it (``bonesim.__version__``; it changes when the bundled data or the session
schema does): a JSON object gets a ``bonesim_version`` key, first; a list
(``cases``, ``burrs``, ``sessions list``) is printed as an object holding the
version and the list under a name, ``{"bonesim_version": ..., "cases": [...]}``.
"""
from __future__ import annotations

import json

__all__ = ["VERSION_KEY", "with_version", "print_json", "print_table"]

#: The key every JSON output carries.
VERSION_KEY = "bonesim_version"


def with_version(obj, items: str = "items") -> dict:
    """``obj`` as a JSON object that says which bonesim made it.

    Parameters
    ----------
    obj : dict or list
        What the command outputs. A dict may hold :data:`VERSION_KEY` only
        with this version (a recording's own version goes under another
        name, such as ``recorded_with``).
    items : str
        The key a list is put under.

    Returns
    -------
    dict
        ``{"bonesim_version": bonesim.__version__, ...obj}``, or
        ``{"bonesim_version": ..., items: obj}`` for a list.
    """
    from bonesim import __version__

    if isinstance(obj, dict):
        if obj.get(VERSION_KEY, __version__) != __version__:
            raise ValueError(f"output holds {VERSION_KEY!r} {obj[VERSION_KEY]!r}, not this "
                             f"bonesim's {__version__!r}")
        return {VERSION_KEY: __version__, **obj}
    if isinstance(obj, (list, tuple)):
        return {VERSION_KEY: __version__, items: list(obj)}
    raise TypeError(f"a JSON output is an object or a list, not {type(obj).__name__}")


def print_json(obj, items: str = "items", default=None) -> None:
    """Print :func:`with_version` of ``obj`` as indented JSON on stdout
    (``default`` as for :func:`json.dumps`, for values JSON lacks)."""
    print(json.dumps(with_version(obj, items), indent=2, default=default))


def print_table(rows: list[dict], cols: list[str]) -> None:
    """Print ``rows`` as text columns ``cols``, each as wide as its widest cell."""
    widths = [max(len(c), *(len(str(r.get(c, ""))) for r in rows)) for c in cols]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print("  ".join(str(r.get(c, "")).ljust(w) for c, w in zip(cols, widths)))
