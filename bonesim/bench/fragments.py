"""Benchmarks of fragment detection (:mod:`bonesim.engine.fragments`).

``fragment_local_ms``
    The local pass after one removal burst on the phantom: a ball of the
    5 mm burr's size (radius 2.5 mm) removed at a random bone voxel of the
    case's target box, then :func:`~bonesim.engine.fragments.find_parts` on
    exactly those removals (median wall time [ms]; p90, max and how many
    bursts had to label the whole body in the detail).
``fragment_global_256_ms``
    The global pass (:func:`~bonesim.engine.fragments.find_parts_global`) of a
    256^3 case of porous bone (thresholded smooth noise, about 60 %% bone,
    with a slab cut through it), from the brick grid to the parts.
``fragment_global_256_scipy_ms``
    :func:`scipy.ndimage.label` (26-connected) of the same volume as a dense
    boolean array, in the same run: the field's reference labeller.
``fragment_global_vs_scipy``
    The ratio of the two.
``fragment_split_8000_ms``
    What the haptic loop spends, between two steps, on one
    :class:`~bonesim.runtime.commands.SplitPart` of a 20^3 (8000-voxel)
    fragment: the flood fill and the ``SPLIT`` records
    (:func:`~bonesim.engine.fragments.publish_part`), done at once. (The
    loop now moves a part of more than ``[split] voxels_per_step`` voxels,
    as this one, in slices over several steps: :mod:`bonesim.engine.split_jobs`,
    and ``haptic_loop_period_split_512k_p99_ms`` in :mod:`bonesim.bench.stalls`.)

Figures are wall-clock on whatever machine runs them; inputs are seeded.
"""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

__all__ = ["GLOBAL_EDGE", "BURST_RADIUS_MM", "SPLIT_EDGE", "bench_fragments"]

#: Edge of the global pass's case [voxels].
GLOBAL_EDGE = 256
#: Radius of the removal burst of the local pass [mm] (the 5 mm burr).
BURST_RADIUS_MM = 2.5


def _ball(radius_vox: float) -> np.ndarray:
    r = int(np.ceil(radius_vox))
    g = np.arange(-r, r + 1)
    d = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return d[(d ** 2).sum(axis=1) <= radius_vox ** 2]


def _local(quick: bool) -> dict:
    from bonesim.engine.fragments import find_parts
    from bonesim.engine.grid import BRICK_SHIFT
    from bonesim.engine.model import make_state
    from bonesim.io.loading import load_model

    model = load_model("phantom", "cutting-5mm")
    g = model.grid
    rng = np.random.default_rng(0)
    dens, _ = g.to_dense()
    box = model.case.target
    lo = np.maximum(np.floor((np.asarray(box.box_min_mm) - g.origin_mm) / g.spacing_mm), 0)
    hi = np.minimum(np.ceil((np.asarray(box.box_max_mm) - g.origin_mm) / g.spacing_mm),
                    np.asarray(g.shape) - 1)
    sub = dens[int(lo[0]):int(hi[0]) + 1, int(lo[1]):int(hi[1]) + 1, int(lo[2]):int(hi[2]) + 1]
    bone = np.argwhere(sub > 0) + lo.astype(np.int64)
    ball = _ball(BURST_RADIUS_MM / g.spacing_mm)
    # brick of every brick coordinate (-1: none)
    bmap = np.full(tuple(((np.asarray(g.shape) + 7) >> BRICK_SHIFT).tolist()), -1, np.int64)
    bc = g.bricks.astype(np.int64)
    inside = (bc >= 0).all(axis=1) & (bc < np.asarray(bmap.shape)).all(axis=1)
    bmap[tuple(bc[inside].T)] = np.flatnonzero(inside)
    st = make_state(model)
    find_parts(st, bone[:1], [0])             # compile and import outside the timing
    n = 40 if quick else 200
    ms = np.empty(n)
    glob = 0
    per_reset = 20
    shape = np.asarray(g.shape)
    for q in range(n):
        if q % per_reset == 0:
            st = make_state(model)
        c = bone[rng.integers(len(bone))]
        ijk = c + ball
        ijk = ijk[((ijk >= 0) & (ijk < shape)).all(axis=1)]
        b3 = ijk >> BRICK_SHIFT
        br = bmap[b3[:, 0], b3[:, 1], b3[:, 2]]
        ok = br >= 0
        off = ((ijk[:, 0] & 7) << 6) | ((ijk[:, 1] & 7) << 3) | (ijk[:, 2] & 7)
        ok[ok] = st.grid.density[br[ok], off[ok]] > 0
        ijk, br, off = ijk[ok], br[ok], off[ok]
        st.grid.density[br, off] = 0.0          # the burst, outside the timing
        stats: dict = {}
        t0 = time.perf_counter()
        find_parts(st, ijk, st.body[br, off], stats=stats)
        ms[q] = (time.perf_counter() - t0) * 1e3
        glob += stats.get("global", 0)
    return {"fragment_local_ms": {
        "value": round(float(np.median(ms)), 3), "unit": "ms",
        "p90_ms": round(float(np.percentile(ms, 90)), 3),
        "max_ms": round(float(ms.max()), 3), "bursts": int(n),
        "bursts_labelled_whole_body": int(glob), "target_ms": 3.0,
        "scenario": "phantom (104^3, 0.5 mm); a 2.5 mm ball removed at a random bone "
                    "voxel of the target box (20 bursts per fresh case), then the "
                    "local pass on its removals"}}


def _porous(edge: int, seed: int = 0) -> np.ndarray:
    """A cube of porous bone: smoothed noise, thresholded, with a one-voxel
    empty rim and an empty slab through the middle (two halves)."""
    from scipy.ndimage import uniform_filter

    rng = np.random.default_rng(seed)
    coarse = uniform_filter(rng.random((edge // 4,) * 3), 3, mode="wrap")
    solid = np.repeat(np.repeat(np.repeat(coarse, 4, 0), 4, 1), 4, 2) < 0.52
    solid[[0, -1], :, :] = solid[:, [0, -1], :] = solid[:, :, [0, -1]] = False
    solid[edge // 2 - 1:edge // 2 + 1] = False
    return solid


def _global(quick: bool) -> dict:
    from scipy.ndimage import label

    from bonesim.engine.fragments import find_parts_global
    from bonesim.engine.grid import Grid

    edge = GLOBAL_EDGE
    solid = _porous(edge)
    grid = Grid.from_dense(solid.astype(np.uint8), spacing_mm=0.5)
    n_b = grid.n_bricks
    max_bodies = 8
    st = SimpleNamespace(grid=grid, body=np.zeros((n_b, 512), np.uint8),
                         alive=np.zeros(max_bodies, np.uint8),
                         bounds=np.zeros((max_bodies, 6), np.int32))
    st.alive[0] = 1
    st.bounds[0, 3:] = edge - 1
    # the removals: the slab's voxels (all of them; the pass looks at their
    # neighbours)
    cut = np.argwhere(np.ones((2, edge - 2, edge - 2), bool)) + (edge // 2 - 1, 1, 1)
    find_parts_global(st, 0, cut[:10])          # compile outside the timing
    reps = 2 if quick else 5
    ours, ref = [], []
    parts = None
    for _ in range(reps):
        t0 = time.perf_counter()
        parts = find_parts_global(st, 0, cut)
        ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _, n_ref = label(solid, np.ones((3, 3, 3), bool))
        ref.append(time.perf_counter() - t0)
    a, b = float(np.median(ours)) * 1e3, float(np.median(ref)) * 1e3
    scen = (f"{edge}^3 porous bone ({solid.mean():.0%} bone, {n_b} bricks), cut in two by "
            "a 2-voxel slab; median of {reps} runs".replace("{reps}", str(reps)))
    return {
        "fragment_global_256_ms": {"value": round(a, 2), "unit": "ms", "target_ms": 100.0,
                                   "parts": len(parts),
                                   "components": int(n_ref), "scenario": scen},
        "fragment_global_256_scipy_ms": {"value": round(b, 2), "unit": "ms",
                                         "scenario": scen + ": scipy.ndimage.label of "
                                         "the dense boolean volume, 26-connected"},
        "fragment_global_vs_scipy": {"value": round(a / b, 3), "unit": "ratio",
                                     "scenario": "fragment_global_256_ms / "
                                                 "fragment_global_256_scipy_ms"},
    }


#: Edge of the split benchmark's fragment [voxels].
SPLIT_EDGE = 20


def _split(quick: bool) -> dict:
    from bonesim.engine.fragments import publish_part
    from bonesim.engine.model import make_model, make_state
    from bonesim.io.burrs import load_burr

    e = SPLIT_EDGE
    lab = np.zeros((e + 8,) * 3, np.uint8)
    lab[4:4 + e, 4:4 + e, 4:4 + e] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
    model = make_model(lab, 0.5, [bone], load_burr("cutting-1mm"))
    args = ((4, 4, 4), (3, 3, 3), (e + 4,) * 3, e ** 3)
    publish_part(make_state(model), 0, *args, 0.0)      # compile outside the timing
    ms = []
    for _ in range(5 if quick else 30):
        st = make_state(model)
        t0 = time.perf_counter()
        publish_part(st, 0, *args, 0.0)
        ms.append((time.perf_counter() - t0) * 1e3)
    return {"fragment_split_8000_ms": {
        "value": round(float(np.median(ms)), 3), "unit": "ms",
        "max_ms": round(float(np.max(ms)), 3), "voxels": e ** 3,
        "scenario": f"SplitPart of a {e}^3 cube of bone (flood fill + SPLIT records), "
                    "as the haptic loop runs it between two steps"}}


def bench_fragments(quick=False) -> dict:
    """All the fragment figures (module docstring)."""
    out = _local(quick)
    out.update(_global(quick))
    out.update(_split(quick))
    return out


if __name__ == "__main__":                    # pragma: no cover
    import json

    print(json.dumps(bench_fragments(), indent=2))
