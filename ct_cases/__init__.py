"""Bundled cases: one folder per case, each holding a ``case.toml`` manifest.

The folder name is the name ``bonesim.io.case.load_case`` accepts for a bundled
case (e.g. ``"phantom"``). Volumes a manifest names are found relative to the
manifest, so a case folder can also be copied anywhere and loaded by path.
"""
from pathlib import Path

CASES_DIR = Path(__file__).resolve().parent
"""Folder holding the bundled case folders (works for installed copies too)."""
