"""Every array a ``Surface.build`` produces, for comparing two trees bit for bit.

Build the same surfaces with two checkouts and compare::

    PYTHONPATH=/path/to/old python scripts/surface_build_arrays.py dump /tmp/old.npz
    PYTHONPATH=/path/to/new python scripts/surface_build_arrays.py dump /tmp/new.npz
    python scripts/surface_build_arrays.py compare /tmp/old.npz /tmp/new.npz

``dump`` builds 40 random small volumes (seeded: shapes 1..39 voxels per axis,
sparse to full occupancy, labels 1..3, uniform or graded densities with
zeros, blocks cut by a sheet of empty voxels, thin-bone tint on every other
one, voxels of 0.1, 0.19 or 0.5 mm), a single voxel, an empty grid, the
phantom at its own voxel and at 0.19 mm (with the model's colours and bone
labels: the tint on) and the synthetic 512 x 512 x 300 CT of
``bonesim bench`` (``bonesim.bench.suite.synthetic_ct``), and saves every
array attribute of each surface and of its shader (positions, normals,
shifts, colours, voxels, alive flags, the voxel -> vertex map, the
triangle and vertex records with their list links, the drawn windings, the
free lists, counters, capacities) with its scalars. ``compare`` lists the
arrays that differ in shape, type or any byte and exits 1 if one does.
The tree is the one on ``PYTHONPATH`` (this script does not add its own).
"""
from __future__ import annotations

import sys

import numpy as np

COLORS = np.array([[0, 0, 0], [230, 220, 190], [200, 60, 50], [40, 90, 210]], dtype=np.uint8)


def _arrays(surf) -> dict:
    out = {}
    for owner, obj in (("surface", surf), ("shader", surf.shader)):
        for k, v in sorted(vars(obj).items()):
            if isinstance(v, np.ndarray):
                out[f"{owner}.{k}"] = v
            elif isinstance(v, (bool, int, float)):
                out[f"{owner}.{k}"] = np.asarray(v)
    return out


def _random_volumes():
    rng = np.random.default_rng(1234)
    for n in range(40):
        shape = tuple(int(s) for s in rng.integers(1, 40, size=3))
        p = rng.choice([0.05, 0.3, 0.6, 0.9, 1.0])
        lab = ((rng.random(shape) < p) * rng.integers(1, 4, size=shape)).astype(np.uint8)
        dens = None
        if n % 3:
            dens = rng.uniform(0.0, 1.0, size=shape).astype(np.float32)
            dens[rng.random(shape) < 0.1] = 0
        if n % 4 == 1 and min(shape) > 4:         # a block cut by an empty sheet
            lab[1:-1, 1:-1, 1:-1] = 1
            lab[:, shape[1] // 2, :] = 0
        bone = [0, 1, 0, 0] if n % 2 else None
        spacing = float(rng.choice([0.19, 0.5] if bone else [0.1, 0.19, 0.5]))
        yield f"random{n}", lab, dens, spacing, bone
    one = np.zeros((1, 1, 1), np.uint8)
    one[0, 0, 0] = 1
    yield "single", one, None, 0.5, None
    yield "empty", np.zeros((5, 5, 5), np.uint8), None, 0.5, None


def _surfaces():
    from bonesim.bench.suite import synthetic_ct
    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface
    from bonesim.io.loading import load_model

    for name, lab, dens, spacing, bone in _random_volumes():
        yield name, Surface.build(Grid.from_dense(lab, dens, spacing_mm=spacing), COLORS,
                                  bone=bone)
    for voxel in (None, 0.19):
        yield f"phantom-{voxel or 'own'}", Surface.of_model(load_model("phantom",
                                                                        voxel_mm=voxel))
    grid = Grid.from_dense(synthetic_ct(), spacing_mm=0.5)
    yield "synthetic-ct", Surface.build(grid, np.array([[0, 0, 0], [230, 220, 200]], np.uint8))


def dump(path: str) -> None:
    out = {}
    for name, surf in _surfaces():
        for k, v in _arrays(surf).items():
            out[f"{name}/{k}"] = v
        print(f"{name}: {surf.n_vertices} vertices, {surf.n_triangles} triangles", flush=True)
    np.savez(path, **out)


def compare(path_a: str, path_b: str) -> int:
    a, b = np.load(path_a), np.load(path_b)
    bad = sorted(set(a.files) ^ set(b.files))
    for k in bad:
        print(f"only in one file: {k}")
    for k in sorted(set(a.files) & set(b.files)):
        x, y = a[k], b[k]
        if x.shape != y.shape or x.dtype != y.dtype or x.tobytes() != y.tobytes():
            print(f"differs: {k} {x.shape} {x.dtype} / {y.shape} {y.dtype}")
            bad.append(k)
    print(f"{len(set(a.files) & set(b.files))} arrays compared, {len(bad)} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "dump":
        dump(sys.argv[2])
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(compare(sys.argv[2], sys.argv[3]))
    else:
        sys.exit("usage: surface_build_arrays.py dump OUT.npz | compare A.npz B.npz")
