"""Files that ship inside the package (``bonesim/data/``), found the same way
from every module, wherever it sits in the package."""
from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_DIR", "data_path"]

#: The package's data folder (``bonesim/data``).
DATA_DIR = Path(__file__).resolve().parent / "data"


def data_path(name: str) -> Path:
    """Path of a file in the package's data folder.

    Parameters
    ----------
    name : str
        File name inside ``bonesim/data`` (e.g. ``"materials.toml"``).

    Returns
    -------
    Path
        Absolute path (the file need not exist).
    """
    return DATA_DIR / name
