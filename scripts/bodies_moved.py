"""Render the phantom with a piece of mastoid split off and moved.

Run from the repository root::

    python scripts/bodies_moved.py [out.png]

(default ``/tmp/bodies_moved.png``): the piece (body 1) is drawn lifted
8 mm toward the case camera and turned 30 degrees, and the main bone shows
the hole it left (:func:`tests.bonesim.render.scenes.bodies_moved`).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bonesim.io.loading import load_model  # noqa: E402
from bonesim.render.gl import select_backend  # noqa: E402
from tests.bonesim.render.scenes import bodies_moved  # noqa: E402


def main(out: str = "/tmp/bodies_moved.png") -> None:
    select_backend(offscreen=True)
    model = load_model("phantom", "cutting-5mm")
    scene, rep = bodies_moved(model, size=(800, 600), visible_subset=False)
    path = scene.screenshot(out)
    counts = {b: s.n_triangles for b, s in rep.body_surfaces.items()}
    print(f"{path}: triangles per body {counts}")
    scene.close()


if __name__ == "__main__":
    main(*sys.argv[1:2])
