#!/usr/bin/env python3
"""Write the shipped plate and distractor meshes (bonesim/data/tools/*.ply)
and their catalogue (bonesim/data/tools/plates.toml).

Each plate is a flat titanium slab with round screw holes, cut from a grid of
square cells and extruded: bottom face (normal -z), top face (+z) and the
walls around the outline and the holes, flat-shaded (a face's vertices carry
its normal). Mesh frame: centred on 0, the slab between z = -t/2 and t/2
[mm]. The distractor is two footplates joined by a rod along +x (its axis).

    python scripts/make_plates.py          # from the repository root
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bonesim.io.meshes import write_ply  # noqa: E402

OUT = ROOT / "bonesim" / "data" / "tools"
#: Cell of the outline grid [mm].
CELL = 0.25
#: Titanium [g/mm^3].
TITANIUM_G_MM3 = 4.5e-3
#: Plate thickness [mm].
THICK = 0.8


def slab(mask: np.ndarray, cell: float, z0: float, z1: float, x0: float, y0: float):
    """A closed, flat-shaded slab over the cells of ``mask`` (nx, ny)."""
    pos, nrm, tris = [], [], []

    def quad(p4, n):
        b = len(pos)
        pos.extend(p4)
        nrm.extend([n] * 4)
        tris.extend([(b, b + 1, b + 2), (b, b + 2, b + 3)])

    nx, ny = mask.shape
    # faces: shared grid nodes per face
    for z, n in ((z0, (0.0, 0.0, -1.0)), (z1, (0.0, 0.0, 1.0))):
        idx = -np.ones((nx + 1, ny + 1), np.int64)
        for i, j in np.argwhere(mask):
            for a, b in ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)):
                if idx[a, b] < 0:
                    idx[a, b] = len(pos)
                    pos.append((x0 + a * cell, y0 + b * cell, z))
                    nrm.append(n)
            c = (idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1])
            if n[2] > 0:
                tris.extend([(c[0], c[1], c[2]), (c[0], c[2], c[3])])
            else:
                tris.extend([(c[0], c[2], c[1]), (c[0], c[3], c[2])])
    padded = np.pad(mask, 1)
    for i, j in np.argwhere(mask):
        x, y = x0 + i * cell, y0 + j * cell
        if not padded[i, j + 1]:          # -x wall
            quad([(x, y, z0), (x, y, z1), (x, y + cell, z1), (x, y + cell, z0)], (-1.0, 0, 0))
        if not padded[i + 2, j + 1]:      # +x wall
            xe = x + cell
            quad([(xe, y, z0), (xe, y + cell, z0), (xe, y + cell, z1), (xe, y, z1)], (1.0, 0, 0))
        if not padded[i + 1, j]:          # -y wall
            quad([(x, y, z0), (x + cell, y, z0), (x + cell, y, z1), (x, y, z1)], (0, -1.0, 0))
        if not padded[i + 1, j + 2]:      # +y wall
            ye = y + cell
            quad([(x, ye, z0), (x, ye, z1), (x + cell, ye, z1), (x + cell, ye, z0)], (0, 1.0, 0))
    return np.array(pos), np.array(tris, np.int64), np.array(nrm)


def outline(size_mm, holes, hole_r=1.0, extra=()):
    """A cell mask of rectangles (``size_mm`` plus ``extra`` boxes (x0, y0,
    x1, y1) in mm from the centre) minus round holes at ``holes`` [mm]."""
    lx, ly = size_mm
    nx, ny = int(round(lx / CELL)), int(round(ly / CELL))
    cx = (np.arange(nx) + 0.5) * CELL - lx / 2
    cy = (np.arange(ny) + 0.5) * CELL - ly / 2
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    mask = np.zeros((nx, ny), bool)
    boxes = list(extra) or [(-lx / 2, -ly / 2, lx / 2, ly / 2)]
    for x0, y0, x1, y1 in boxes:
        mask |= (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
    for hx, hy in holes:
        mask &= (X - hx) ** 2 + (Y - hy) ** 2 > hole_r ** 2
    return mask, -lx / 2, -ly / 2


def _mass_g(mask, thick):
    return float(mask.sum() * CELL * CELL * thick * TITANIUM_G_MM3)


def straight4():
    mask, x0, y0 = outline((24.0, 5.0), [(-9.0, 0), (-3.0, 0), (3.0, 0), (9.0, 0)])
    return slab(mask, CELL, -THICK / 2, THICK / 2, x0, y0), _mass_g(mask, THICK)


def lplate():
    # arms: 20 mm along x at the bottom, 14 mm along y at the left, 5 mm wide
    boxes = [(-10.0, -7.0, 10.0, -2.0), (-10.0, -7.0, -5.0, 7.0)]
    holes = [(6.0, -4.5), (0.0, -4.5), (-7.5, -4.5), (-7.5, 4.0)]
    mask, x0, y0 = outline((20.0, 14.0), holes, extra=boxes)
    return slab(mask, CELL, -THICK / 2, THICK / 2, x0, y0), _mass_g(mask, THICK)


def distractor():
    """Two 7 x 6 mm footplates 16 mm apart (centres at x = -/+ 11.5 mm),
    each with two holes, joined by a 1.5 mm square rod along x above them."""
    parts, mass = [], 0.0
    for sx in (-1, 1):
        m, x0, y0 = outline((7.0, 6.0), [(-1.8, 0.0), (1.8, 0.0)], hole_r=0.9)
        parts.append(slab(m, CELL, -THICK / 2, THICK / 2, x0 + sx * 11.5, y0))
        mass += _mass_g(m, THICK)
    rod = np.ones((int(26.0 / CELL), int(1.5 / CELL)), bool)
    parts.append(slab(rod, CELL, THICK / 2, THICK / 2 + 1.5, -13.0, -0.75))
    mass += _mass_g(rod, 1.5)
    pos, tris, nrm = [], [], []
    for p, t, n in parts:
        tris.append(t + sum(len(q) for q in pos))
        pos.append(p)
        nrm.append(n)
    return (np.concatenate(pos), np.concatenate(tris), np.concatenate(nrm)), mass


CATALOGUE = [
    ("straight-4", "plate", "plate_straight4.ply", straight4,
     "straight 4-hole plate, 24 x 5 x 0.8 mm"),
    ("l-plate", "plate", "plate_l.ply", lplate, "L plate, 20 x 14 mm arms 5 mm wide, 4 holes"),
    ("distractor", "distractor", "distractor.ply", distractor,
     "two 7 x 6 mm footplates 16 mm apart on a 1.5 mm rod along x"),
]


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# Plates and distractors (written by scripts/make_plates.py; see",
             "# bonesim/io/plates.py for the fields). Mesh frame [mm]: centred, the",
             "# plate's bottom face at z = -0.4 facing -z; a distractor's axis is +x.", ""]
    for name, kind, fname, make, desc in CATALOGUE:
        (pos, tris, nrm), mass_g = make()
        write_ply(OUT / fname, pos, tris, nrm)
        lines += ["[[plate]]", f'name = "{name}"', f'kind = "{kind}"',
                  f'description = "{desc}"', f'mesh = "{fname}"',
                  f"mass_g = {mass_g:.4f}", "sample_offset_mm = 0.15",
                  "stiffness_n_per_mm = 0.002", "samples = 400"]
        if kind == "distractor":
            lines.append("axis = [1.0, 0.0, 0.0]")
        lines.append("")
        print(f"{fname}: {len(pos)} vertices, {len(tris)} triangles, {mass_g:.3f} g")
    (OUT / "plates.toml").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
