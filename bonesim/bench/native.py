"""The haptic step at native resolution: the phantom generated at 0.19 mm and
0.1 mm voxels against the same phantom at 0.5 mm, stepped in one run.

Every model takes the same device samples (the demo mastoidectomy's path
where the drill runs, with the default burr), interleaved step by step in a
rotating order, so the ratios compare steps taken under the same load. At
0.5 mm the step is the per-voxel kernel (the budget does not bind); at 0.19
and 0.1 mm it is the fixed-budget step (:mod:`bonesim.engine.haptics_budget`).

The phantom at 0.1 mm is 520^3 voxels (140 M); its engine grid is built on a
crop: the box the stretch of path drills, widened by the burr's radius and
:data:`CROP_MARGIN_MM` (the mastoid cortex and antrum the path enters).

Each state's event rings are written once before the timing, so that no
step pays for mapping their pages (a running loop's rings are long mapped).

The floor of the fixed-budget step is the memory it must touch: the
brick table of the burr's neighbourhood (``block_bricks``) and one density
per sample read through it (:func:`budget_floor_pass`), at the same
positions, timed interleaved with the step.
"""
from __future__ import annotations

import time

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, voxel_offset
from bonesim.engine.haptics import block_bricks

__all__ = ["CROP_MARGIN_MM", "NATIVE_VOXELS_MM", "budget_floor_pass", "bench_native_step"]

#: Native voxel sizes benchmarked [mm].
NATIVE_VOXELS_MM = (0.19, 0.1)
#: Margin around the drilled box of the 0.1 mm crop [mm].
CROP_MARGIN_MM = 3.0


@njit(cache=True, nogil=True)
def _floor(keys, vals, density, origin, spacing, samples, pos, radius, lbrick):
    lo0, lo1, lo2, _ = block_bricks(keys, vals, pos, radius, origin, spacing, lbrick)
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    inv = 1.0 / spacing
    c0 = (pos[0] - origin[0]) * inv + 0.5
    c1 = (pos[1] - origin[1]) * inv + 0.5
    c2 = (pos[2] - origin[2]) * inv + 0.5
    total = 0.0
    for q in range(samples.shape[0]):
        i = int(c0 + samples[q, 0] * inv - lo0) + lo0
        j = int(c1 + samples[q, 1] * inv - lo1) + lo1
        k = int(c2 + samples[q, 2] * inv - lo2) + lo2
        b = lbrick[(i >> BRICK_SHIFT) - b0, (j >> BRICK_SHIFT) - b1, (k >> BRICK_SHIFT) - b2]
        if b >= 0:
            total += density[b, voxel_offset(i, j, k)]
    return total


def budget_floor_pass(grid, samples, pos_mm, radius_mm: float, lbrick) -> float:
    """The fixed-budget step's floor: fill the brick table around the burr,
    then read one fine-voxel density per sample through it (offsets along
    the case axes; no tool frame, force, removal or events).

    Parameters
    ----------
    grid : bonesim.engine.grid.Grid
    samples : (n, >=3) float32
        Sample offsets from the burr's centre [mm].
    pos_mm : (3,) float64
        Burr centre, case frame [mm].
    radius_mm : float
        Burr radius [mm].
    lbrick : (nb, nb, nb) int32
        Brick-table scratch (a state's ``_lbrick``).

    Returns
    -------
    float
        The sum of the densities read.
    """
    samples = np.asarray(samples)
    if samples.ndim != 2 or samples.shape[1] < 3:
        raise ValueError(f"samples must be (n, >=3), got {samples.shape}")
    return _floor(grid.keys, grid.vals, grid.density, np.asarray(grid.origin_mm, np.float64),
                  float(grid.spacing_mm), samples, np.asarray(pos_mm, np.float64),
                  float(radius_mm), lbrick)


def _path(burr_name: str, n: int):
    """``n`` samples of the demo path from where the drill starts."""
    from bonesim.io.case import load_case
    from bonesim.io.toolpath import demo_trajectory

    traj = demo_trajectory(load_case("phantom"), burr_name)
    start = int(np.flatnonzero(traj.drill)[0])
    return [traj.sample(q) for q in range(start, min(start + n, len(traj.t_s)))]


def _crop_model(voxel_mm: float, burr_name: str, lo_mm, hi_mm):
    """The phantom at ``voxel_mm``, its engine grid cropped to the box
    ``lo_mm .. hi_mm`` (case frame)."""
    from bonesim.engine.model import make_model
    from bonesim.io.burrs import load_burr
    from bonesim.io.case import load_case

    c = load_case("phantom", voxel_mm=voxel_mm)
    vol = c.load_volume()
    c = c.resolved(vol)
    o = np.asarray(vol.origin_mm, float)
    lo = np.maximum(np.floor((np.asarray(lo_mm) - o) / vol.spacing_mm).astype(int), 0)
    hi = np.minimum(np.ceil((np.asarray(hi_mm) - o) / vol.spacing_mm).astype(int) + 1,
                    vol.labels.shape)
    labels = np.ascontiguousarray(vol.labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
    model = make_model(labels, vol.spacing_mm, c.structures, load_burr(burr_name),
                       origin_mm=o + lo * vol.spacing_mm, name=f"phantom-crop-{voxel_mm:g}",
                       case=None)
    return model, tuple(int(x) for x in labels.shape)


def bench_native_step(quick=False) -> dict:
    """p99 of the haptic step on the phantom at 0.19 mm and 0.1 mm (crop)
    and their ratios to the 0.5 mm step, same samples, same run."""
    from bonesim.engine.model import make_state, step
    from bonesim.io.burrs import DEFAULT_BURR, load_burr
    from bonesim.io.loading import load_model, warmup

    warmup()
    n = 1500 if quick else 6000
    burr = load_burr(DEFAULT_BURR)
    path = _path(DEFAULT_BURR, n)
    pts = np.array([s.pos_mm for s in path])
    lo = pts.min(axis=0) - burr.radius_mm - CROP_MARGIN_MM
    hi = pts.max(axis=0) + burr.radius_mm + CROP_MARGIN_MM
    models = {"05": (load_model("phantom", DEFAULT_BURR), None),
              "019": (load_model("phantom", DEFAULT_BURR, voxel_mm=0.19), None)}
    models["010"] = _crop_model(0.1, DEFAULT_BURR, lo, hi)
    states = {k: make_state(m) for k, (m, _) in models.items()}
    for st in states.values():
        # the event rings written once before timing: their pages are mapped
        # (a fresh ring maps a page per ~70 records on first write, which
        # would charge the 0.1 mm step's many removals with page faults)
        for ring in (st.tissue, st.touched):
            for f in ring.fields.values():
                f[...] = 0
    keys = list(models)
    # compile every kernel outside the timing (a throwaway state each)
    for k, (m, _) in models.items():
        st = make_state(m)
        for smp in path[:20]:
            step(m, st, smp)
        budget_floor_pass(m.grid, m.stencil.packed, path[0].pos_mm, burr.radius_mm,
                          st._lbrick)
    ns = {k: np.empty(len(path), np.int64) for k in keys}
    floor_ns = {k: np.empty(len(path), np.int64) for k in keys}
    perf = time.perf_counter_ns
    for q, smp in enumerate(path):
        for r in range(len(keys)):
            k = keys[(q + r) % len(keys)]
            m, st = models[k][0], states[k]
            t0 = perf()
            budget_floor_pass(st.grid, m.stencil.packed, smp.pos_mm, burr.radius_mm,
                              st._lbrick)
            t1 = perf()
            step(m, st, smp)
            ns[k][q] = perf() - t1
            floor_ns[k][q] = t1 - t0
    us = {k: v / 1e3 for k, v in ns.items()}
    fus = {k: v / 1e3 for k, v in floor_ns.items()}

    def pct(k, p):
        return float(np.percentile(us[k], p))

    base = pct("05", 99)
    out = {}
    for k, v in (("019", 0.19), ("010", 0.1)):
        m = models[k][0]
        detail = {"voxel_mm": v, "burr": DEFAULT_BURR, "steps": len(path),
                  "samples": m.stencil.n, "sample_spacing_mm": m.stencil.spacing_mm,
                  "removal_cell_voxels": m.budget.cell,
                  "removal_budget_voxels": m.budget.removal_voxels[0],
                  "budget_binding": m.budget.binding,
                  "p50_us": round(pct(k, 50), 2), "removed": states[k].n_removed,
                  "grid": list(m.grid.shape)}
        if k == "010":
            detail["crop"] = ("the phantom at 0.1 mm cropped to the drilled box of the path "
                              f"widened by the burr radius and {CROP_MARGIN_MM:g} mm")
        out[f"haptic_step_native_{k}_p99_us"] = {
            "value": round(pct(k, 99), 2), "unit": "us",
            "what": f"p99 of the haptic step on the phantom at {v:g} mm voxels, the demo "
                    "path where it drills, default burr", **detail}
        out[f"haptic_step_native_{k}_vs_05"] = {
            "value": round(pct(k, 99) / base, 3), "unit": "x",
            "what": f"haptic_step_native_{k}_p99_us / the p99 of the same samples on the "
                    "0.5 mm phantom, stepped interleaved in one run",
            "p99_05_us": round(base, 2), "p50_05_us": round(pct("05", 50), 2),
            "p50_ratio": round(pct(k, 50) / pct("05", 50), 3)}
        out[f"haptic_step_native_{k}_vs_floor"] = {
            "value": round(pct(k, 50) / float(np.percentile(fus[k], 50)), 3), "unit": "x",
            "what": "p50 of the fixed-budget step / p50 of its floor: the memory it must "
                    "touch (the brick table around the burr and one fine-voxel density "
                    "per sample read through it), timed interleaved at the same positions",
            "floor_p50_us": round(float(np.percentile(fus[k], 50)), 2)}
    return out
