"""Benchmarks behind ``bonesim bench``.

Each benchmark returns ``{"value": number, "unit": str, ...detail}``. Inputs
are generated deterministically (fixed seeds), kernels are compiled before
timing, and references (scikit-image's marching cubes, a from-scratch
tessellation) are timed in the same run on the same data, so ratios are
comparable across machines. Figures are wall-clock on whatever machine runs
them; they are reported, never asserted in tests.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bonesim.bench.tools import ball_offsets, floor_scratch, remove_voxels, stencil_density_pass

__all__ = ["ON_REQUEST", "CT_SHAPE", "bench_haptic_step", "bench_surface", "synthetic_ct",
           "bench_ct512", "bench_simulate", "bench_haptic_loop",
           "bench_haptic_loop_rendering", "bench_render", "bench_audio", "bench_dust",
           "bench_recording", "bench_tutor", "bench_monitor", "bench_load",
           "ByName", "BENCHMARKS", "run_benchmarks"]

#: Synthetic CT size for the tessellation benchmarks [voxels].
CT_SHAPE = (512, 512, 300)


def _pct(values, q) -> float:
    return float(np.percentile(np.asarray(values, float), q))


# ----------------------------------------------------------------- haptics
def _time_haptic_steps(oversample: int, n: int, with_floor: bool):
    """Step times [ns] of the 7 mm cutting burr half immersed in a bone block,
    sweeping slowly through fresh bone, and (optionally) the floor's times at
    the same positions; returns ``(model, step_ns, floor_ns)``."""
    from types import SimpleNamespace

    from bonesim.io.burrs import load_burr
    from bonesim.engine.model import Sample, make_model, make_state, step

    burr = load_burr("cutting-7mm")
    labels = np.zeros((120, 120, 60), np.uint8)
    labels[:, :, :40] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
    model = make_model(labels, 0.5, [bone], burr, oversample=oversample)
    top = 40 * 0.5 - 0.25                      # top face of the block [mm]
    per_reset = 500
    ns = np.empty(n, dtype=np.int64)
    floor_ns = np.zeros(n, dtype=np.int64)
    axis = np.array([0.3, 0.0, -1.0])
    perf = time.perf_counter_ns
    samples = model.stencil.packed
    scratch = floor_scratch(burr.radius_mm, 0.5)
    stencil_density_pass(model.grid, samples, np.zeros(3), burr.radius_mm, scratch)
    state = None
    for q in range(n):
        if q % per_reset == 0:
            state = make_state(model)          # fresh bone, outside the timing
        u = q % per_reset
        pos = np.array([10.0 + (0.08 * u) % 40.0, 10.0 + 8.0 * ((q // per_reset) % 5), top])
        smp = Sample(q * 1e-3, pos, axis, True, burr.default_speed_rpm, 1)
        t0 = perf()
        if with_floor:
            stencil_density_pass(state.grid, samples, pos, burr.radius_mm, scratch)
        t1 = perf()
        step(model, state, smp)
        ns[q] = perf() - t1
        floor_ns[q] = t1 - t0
    return model, ns, floor_ns


#: Bodies the multi-body figure splits the bench block into.
BENCH_BODIES = 8
#: Edge of the cubes the bodies interleave in [voxels]: every body is within
#: the burr's reach wherever it cuts.
BENCH_BODY_CELL = 4


def _interleaved_bodies(model) -> list:
    """Voxel lists (body frame) of bodies 1..7 of a 3D checkerboard of cubes."""
    g = np.mgrid[0:model.grid.shape[0], 0:model.grid.shape[1], 0:model.grid.shape[2]]
    c = g // BENCH_BODY_CELL
    body = (c[0] % 2) + 2 * (c[1] % 2) + 4 * (c[2] % 2)
    ijk = g.reshape(3, -1).T.astype(np.int32)
    return [ijk[body.ravel() == b] for b in range(1, BENCH_BODIES)]


def _time_multibody_steps(n: int):
    """Step times [ns] of the same sweep as :func:`_time_haptic_steps` on the
    block as one body and split into :data:`BENCH_BODIES` interleaved bodies
    (identity poses), stepped alternately with the same samples; returns
    ``(one_ns, many_ns)``."""
    from types import SimpleNamespace

    from bonesim.engine.bodies import split_body
    from bonesim.io.burrs import load_burr
    from bonesim.engine.model import Sample, make_model, make_state, step

    burr = load_burr("cutting-7mm")
    labels = np.zeros((120, 120, 60), np.uint8)
    labels[:, :, :40] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
    model = make_model(labels, 0.5, [bone], burr)
    parts = _interleaved_bodies(model)
    top = 40 * 0.5 - 0.25
    per_reset = 500
    one_ns = np.empty(n, dtype=np.int64)
    many_ns = np.empty(n, dtype=np.int64)
    axis = np.array([0.3, 0.0, -1.0])
    perf = time.perf_counter_ns
    one = many = None
    for q in range(n):
        if q % per_reset == 0:
            one, many = make_state(model), make_state(model)
            for b, ijk in enumerate(parts, start=1):
                split_body(many, 0, ijk, b)
        u = q % per_reset
        pos = np.array([10.0 + (0.08 * u) % 40.0, 10.0 + 8.0 * ((q // per_reset) % 5), top])
        smp = Sample(q * 1e-3, pos, axis, True, burr.default_speed_rpm, 1)
        for st, out in ((one, one_ns), (many, many_ns)) if q % 2 else \
                ((many, many_ns), (one, one_ns)):
            t0 = perf()
            step(model, st, smp)
            out[q] = perf() - t0
    return one_ns, many_ns


def bench_haptic_step(quick=False) -> dict:
    """Haptic step with the 7 mm cutting burr half immersed in a bone block
    (2x oversampling), its floor, and the same step at 4x oversampling."""
    from bonesim.io.loading import warmup

    warmup()
    n = 2000 if quick else 20000
    model, ns, floor_ns = _time_haptic_steps(2, n, True)
    us, floor_us = ns / 1e3, floor_ns / 1e3
    model4, ns4, _ = _time_haptic_steps(4, n // 4, False)
    us4 = ns4 / 1e3
    one_ns, many_ns = _time_multibody_steps(n // 2)
    one_p99, many_p99 = _pct(one_ns / 1e3, 99), _pct(many_ns / 1e3, 99)
    return {
        "haptic_step_floor_us": {
            "value": round(_pct(floor_us, 50), 2), "unit": "us",
            "what": "p50 of one pass over the 7 mm stencil's samples that only looks up "
                    "each sample's voxel density, at the step's positions",
            "samples": model.stencil.n},
        "haptic_step_vs_floor": {
            "value": round(_pct(us, 50) / _pct(floor_us, 50), 2), "unit": "x",
            "what": "haptic_step_7mm_p50_us / haptic_step_floor_us, measured interleaved"},
        "haptic_step_7mm_p50_us": {"value": round(_pct(us, 50), 2), "unit": "us",
                                   "samples": model.stencil.n, "steps": n,
                                   "oversample": model.oversample},
        "haptic_step_7mm_p99_us": {"value": round(_pct(us, 99), 2), "unit": "us",
                                   "samples": model.stencil.n, "steps": n},
        "haptic_step_7mm_4x_p99_us": {"value": round(_pct(us4, 99), 2), "unit": "us",
                                      "samples": model4.stencil.n, "steps": len(ns4),
                                      "oversample": model4.oversample,
                                      "p50_us": round(_pct(us4, 50), 2)},
        "haptic_step_4x_vs_2x_p50": {
            "value": round(_pct(us4, 50) / _pct(us, 50), 2), "unit": "x",
            "what": "p50 of the 7 mm step at 4x oversampling / at 2x (one lookup per "
                    "sample), same run; at 4x on 0.5 mm voxels (0.125 mm) the fixed "
                    "budget binds: the fixed-budget step (bonesim.engine.haptics_budget, "
                    "the 2x sample count)"},
        "haptic_step_7mm_8bodies_p99_us": {
            "value": round(many_p99, 2), "unit": "us", "steps": len(many_ns),
            "what": f"the 7 mm step with the block split into {BENCH_BODIES} interleaved "
                    f"bodies of {BENCH_BODY_CELL}-voxel cubes (all within reach, identity "
                    "poses)", "one_body_p99_us": round(one_p99, 2)},
        "haptic_step_8bodies_vs_1body_p99": {
            "value": round(many_p99 / one_p99, 3), "unit": "x",
            "what": "haptic_step_7mm_8bodies_p99_us / the one-body p99, stepped alternately"},
    }


# ----------------------------------------------------------------- surface
def bench_surface(quick=False) -> dict:
    """From-scratch and incremental tessellation of the phantom."""
    from bonesim.io.loading import load_model
    from bonesim.engine.surface import Surface, warmup

    warmup()
    model = load_model("phantom", "cutting-5mm")
    grid = model.grid.copy()
    reps = 2 if quick else 5
    full = []
    for _ in range(reps):
        t0 = time.perf_counter()
        surf = Surface.of_model(model, grid)
        full.append(time.perf_counter() - t0)
    t_full = float(np.median(full))
    # incremental: remove burr-shaped blobs of ~1000 voxels at surface vertices
    rng = np.random.default_rng(0)
    ball = ball_offsets(6.2)                   # ~1000 voxels
    per_k = []
    reshaded = []
    n_blobs = 10 if quick else 60
    verts = surf.ijk[surf.vertex_slots].copy()          # the surface voxels
    for _ in range(n_blobs):
        c = verts[rng.integers(len(verts))]
        ijk = remove_voxels(grid, c + ball)
        t0 = time.perf_counter()
        st = surf.update(grid, ijk)         # always: the voxels are gone either way
        dt = time.perf_counter() - t0
        if len(ijk) >= 200:                 # time only blobs that cut real bone
            per_k.append(dt * 1000.0 / len(ijk))
            reshaded.append(st["vertices_reshaded"] * 1000.0 / len(ijk))
    per_k = np.array(per_k)
    # the fixed cost of an update: one voxel removed at a surface vertex
    one = []
    for _ in range(20 if quick else 100):
        ijk = remove_voxels(grid, verts[rng.integers(len(verts))][None])
        if len(ijk):
            t0 = time.perf_counter()
            surf.update(grid, ijk)
            one.append(time.perf_counter() - t0)
    return {
        "tessellate_phantom_s": {"value": round(t_full, 4), "unit": "s",
                                 "vertices": int(surf.n_vertices),
                                 "triangles": int(surf.n_triangles)},
        "retessellate_1000_p99_ms": {"value": round(_pct(per_k, 99) * 1e3, 3), "unit": "ms",
                                     "p50_ms": round(_pct(per_k, 50) * 1e3, 3),
                                     "blobs": int(len(per_k))},
        "retessellate_speedup_vs_full": {
            "value": round(t_full / float(np.mean(per_k)), 1), "unit": "x",
            "reference": "Surface.build of the phantom vs incremental update per 1000 "
                         "removed voxels (mean)",
            "vertices_reshaded_per_1000": round(float(np.median(reshaded)), 1),
            "surface_vertices": int(surf.n_vertices),
            "what": "bounded by surface_vertices / vertices_reshaded_per_1000 when a "
                    "refreshed vertex costs what a built one does"},
        "retessellate_one_voxel_us": {
            "value": round(_pct(np.array(one), 50) * 1e6, 1), "unit": "us",
            "what": "p50 of an update removing one surface voxel (the fixed cost of "
                    "an update: the refresh window's normals box and tint rays)"},
    }


def synthetic_ct(shape=CT_SHAPE, seed=0) -> np.ndarray:
    """A skull-like label volume: an ellipsoidal shell with inner ridges.

    Returns
    -------
    (nx, ny, nz) uint8
        1 where bone.
    """
    rng = np.random.default_rng(seed)
    nx, ny, nz = shape
    x = (np.arange(nx, dtype=np.float32) - nx / 2) / (nx * 0.45)
    y = (np.arange(ny, dtype=np.float32) - ny / 2) / (ny * 0.45)
    out = np.zeros(shape, np.uint8)
    r2xy = x[:, None] ** 2 + y[None, :] ** 2
    thick = 0.035
    blobs = rng.uniform(-0.5, 0.5, size=(12, 3)).astype(np.float32)
    for k in range(nz):
        z = (k - nz / 2) / (nz * 0.48)
        r = np.sqrt(r2xy + z * z)
        slab = (r < 1.0) & (r > 1.0 - thick)
        for b in blobs:                       # dense inner structures (petrous-like)
            slab |= ((x[:, None] - b[0]) ** 2 + (y[None, :] - b[1]) ** 2
                     + (z - b[2]) ** 2) < 0.004
        out[:, :, k] = slab
    return out


def bench_ct512(quick=False) -> dict:
    """Surface stage of a synthetic 512x512x300 CT beside skimage marching cubes."""
    from skimage.measure import marching_cubes

    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface, warmup

    warmup()
    labels = synthetic_ct()
    grid = Grid.from_dense(labels, spacing_mm=0.5)
    colors = np.array([[0, 0, 0], [230, 220, 200]], np.uint8)
    reps = 1 if quick else 3
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        surf = Surface.build(grid, colors)
        ts.append(time.perf_counter() - t0)
    vol = labels.astype(np.float32)
    t0 = time.perf_counter()
    verts, faces, _, _ = marching_cubes(vol, level=0.5, spacing=(0.5, 0.5, 0.5))
    t_mc = time.perf_counter() - t0
    t_ours = float(np.median(ts))
    return {
        "tessellate_ct512_s": {"value": round(t_ours, 3), "unit": "s",
                               "shape": list(CT_SHAPE), "vertices": int(surf.n_vertices),
                               "triangles": int(surf.n_triangles),
                               "bone_voxels": int(labels.sum())},
        "marching_cubes_ct512_s": {"value": round(t_mc, 3), "unit": "s",
                                   "reference": "skimage.measure.marching_cubes, same "
                                                "volume", "triangles": int(len(faces)),
                                   "ratio_ours_over_mc": round(t_ours / t_mc, 3)},
    }


# -------------------------------------------------------------- simulate
def bench_simulate(quick=False) -> dict:
    """Wall time of a warm ``bonesim simulate`` of a 5 s trajectory (new process)."""
    from bonesim.io.case import load_case
    from bonesim.io.burrs import DEFAULT_BURR
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.io.trajectory import Trajectory, write_trajectory

    traj = demo_trajectory(load_case("phantom"), DEFAULT_BURR)
    keep = traj.t_s <= 5.0
    cut = Trajectory(t_s=traj.t_s[keep], pos_mm=traj.pos_mm[keep], axis=traj.axis[keep],
                     drill=traj.drill[keep], speed_rpm=traj.speed_rpm[keep],
                     direction=traj.direction[keep])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "five_seconds.csv"
        write_trajectory(path, cut)
        cmd = [sys.executable, "-m", "bonesim.cli", "simulate", "--case", "phantom",
               "--burr", DEFAULT_BURR, "--trajectory", str(path), "--json"]
        env = dict(os.environ)
        subprocess.run(cmd, check=True, capture_output=True, env=env)   # warm the cache
        t0 = time.perf_counter()
        res = subprocess.run(cmd, check=True, capture_output=True, env=env)
        wall = time.perf_counter() - t0
    import json

    summary = json.loads(res.stdout)
    return {"simulate_warm_s": {"value": round(wall, 3), "unit": "s",
                                "trajectory_s": round(float(cut.t_s[-1]), 3),
                                "voxels_removed": summary["voxels_removed"],
                                "steps": summary["steps"]}}


def _loop_for_bench(seconds: float):
    """A haptic loop on the phantom playing the demo path where it drills."""
    from bonesim.io.case import load_case
    from bonesim.io.burrs import DEFAULT_BURR
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.io.loading import load_model

    model = load_model("phantom", DEFAULT_BURR)
    traj = demo_trajectory(load_case("phantom"), DEFAULT_BURR)
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:])
    return model, HapticLoop(model, device=("scripted", traj), run_s=seconds)


def bench_haptic_loop(quick=False) -> dict:
    """Period of the 1 kHz haptic loop process while a consumer keeps the
    surface up to date (no rendering)."""
    from bonesim.engine.replica import TissueReplica

    seconds = 2.0 if quick else 6.0
    model, loop = _loop_for_bench(seconds)
    try:
        loop.start()
        consumer = TissueReplica(model, loop.state, surface=True)
        while loop.running:
            consumer.drain()
            time.sleep(1.0 / 60.0)
        p = loop.recent_periods(int(seconds * 1000))[1:] * 1e3
        realtime = bool(loop.status["realtime"])
    finally:
        loop.close()
    return {"haptic_loop_period_p99_ms": {
        "value": round(_pct(p, 99), 3), "unit": "ms", "p50_ms": round(_pct(p, 50), 3),
        "max_ms": round(float(p.max()), 3), "rate_hz": round(1e3 / float(p.mean()), 1),
        "periods": int(len(p)), "realtime_priority": realtime,
        "setup": "haptic loop in its own process (scripted device, phantom, cutting-5mm); "
                 "main process drains removals into the surface at 60 Hz"}}


def bench_haptic_loop_rendering(quick=False) -> dict:
    """Haptic loop period while the window renders the phantom at full speed
    (offscreen software OpenGL, frames back to back, the app's own frame
    callback: surface, dust, tool and HUD updates)."""
    from bonesim.apps.simulator import App
    from bonesim.io.case import load_case
    from bonesim.io.burrs import DEFAULT_BURR
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.render import gl

    traj = demo_trajectory(load_case("phantom"), DEFAULT_BURR)
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:])
    frames = 100 if quick else 300
    app = App("phantom", DEFAULT_BURR, script=traj, offscreen=True, size=(800, 600),
              sound=False)
    try:
        app.start()
        head0 = app.loop.steps_measured
        t0 = time.perf_counter()
        out = app.window.run_offscreen(frames, realtime=False)
        wall = time.perf_counter() - t0
        n = app.loop.steps_measured - head0
        p = app.loop.recent_periods(n)[1:] * 1e3
        realtime = bool(app.loop.status["realtime"])
    finally:
        app.close()
    info = gl.select_backend(offscreen=True)
    return {"haptic_loop_period_p99_ms_rendering": {
        "value": round(_pct(p, 99), 3), "unit": "ms", "p50_ms": round(_pct(p, 50), 3),
        "max_ms": round(float(p.max()), 3), "rate_hz": round(1e3 / float(p.mean()), 1),
        "periods": int(len(p)), "frames": out["frames"],
        "frame_hz": round(out["frames"] / wall, 1), "realtime_priority": realtime,
        "gl": {"backend": info.backend, "renderer": info.renderer,
               "software": info.software,
               "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS", "default (one per core)")},
        "size_px": [800, 600]}}


def bench_render(quick=False) -> dict:
    from bonesim.render.bench import bench_render as run

    return run(quick=quick)


def bench_audio(quick=False) -> dict:
    from bonesim.bench.sound import bench_audio as run

    return run(quick=quick)


def bench_dust(quick=False) -> dict:
    from bonesim.bench.dust import bench_dust as run

    return run(quick=quick)


def bench_recording(quick=False) -> dict:
    from bonesim.bench.record import bench_recording as run

    return run(quick=quick)


def bench_tutor(quick=False) -> dict:
    from bonesim.bench.tutor import bench_tutor as run

    return run(quick=quick)


def bench_monitor(quick=False) -> dict:
    from bonesim.bench.monitor import bench_monitor as run

    return run(quick=quick)


def bench_load(quick=False) -> dict:
    from bonesim.bench.load import bench_load as run

    return run(quick=quick)


class ByName:
    """A benchmark found by its dotted name, imported only when it runs.

    Parameters
    ----------
    ref : str
        ``"package.module:function"``; the function takes ``quick`` and
        returns ``{figure name: {"value": ..., "unit": ..., ...}}``.

    The bench reaches the research package's benchmarks (``metrics/bench``)
    this way: ``bonesim`` never imports ``metrics`` (the import-linter
    contracts in ``pyproject.toml``), and ``tests/bonesim/test_layers.py``
    checks that every name in :data:`BENCHMARKS` resolves.
    """

    def __init__(self, ref: str):
        module, _, function = ref.partition(":")
        if not module or not function:
            raise ValueError(f"benchmark reference {ref!r} is not 'module:function'")
        self.ref = ref
        self.module = module
        self.__name__ = function

    def resolve(self):
        """The benchmark function (imports its module); a missing module is
        one line (:class:`~bonesim.errors.BonesimError`)."""
        import importlib

        from bonesim.errors import BonesimError

        try:
            mod = importlib.import_module(self.module)
        except ImportError as exc:
            raise BonesimError(f"benchmark {self.ref} cannot be loaded ({exc}); the "
                               "research benchmarks need the metrics package beside "
                               "bonesim") from None
        return getattr(mod, self.__name__)

    def __call__(self, quick=False) -> dict:
        return self.resolve()(quick=quick)

    def __repr__(self) -> str:
        return f"ByName({self.ref!r})"


def _by_name(names, ref: str) -> dict:
    """``names`` (one or several figures one run gives) -> one :class:`ByName`."""
    fn = ByName(ref)
    return dict.fromkeys((names,) if isinstance(names, str) else names, fn)


#: The benchmarks: figure name -> a function of ``quick`` returning that
#: figure (and maybe others; one run gives them all). Benchmarks outside this
#: module are named by their dotted names (:class:`ByName`).
BENCHMARKS = {
    "haptic_step_7mm_p50_us": bench_haptic_step,
    "haptic_step_7mm_p99_us": bench_haptic_step,
    "haptic_step_floor_us": bench_haptic_step,
    "haptic_step_vs_floor": bench_haptic_step,
    "haptic_step_7mm_4x_p99_us": bench_haptic_step,
    "haptic_step_4x_vs_2x_p50": bench_haptic_step,
    "haptic_step_7mm_8bodies_p99_us": bench_haptic_step,
    "haptic_step_8bodies_vs_1body_p99": bench_haptic_step,
    **_by_name(tuple(f"haptic_step_native_{v}_{f}" for v in ("019", "010")
                     for f in ("p99_us", "vs_05", "vs_floor")),
               "bonesim.bench.native:bench_native_step"),
    **_by_name(("world_step_vs_step_p50", "world_step_7mm_p99_us"),
               "bonesim.bench.world:bench_world_step"),
    "retessellate_1000_p99_ms": bench_surface,
    "retessellate_speedup_vs_full": bench_surface,
    "retessellate_one_voxel_us": bench_surface,
    "tessellate_phantom_s": bench_surface,
    **_by_name("surface_roughness_deg", "bonesim.bench.surface_quality:bench_surface_roughness"),
    "tessellate_ct512_s": bench_ct512,
    "marching_cubes_ct512_s": bench_ct512,
    **_by_name(("tessellate_ct512_vs_flying_edges", "flying_edges_ct512_s"),
               "bonesim.bench.native_surface:bench_flying_edges"),
    **_by_name(("render_update_native_019_ms", "render_fps_native_019"),
               "bonesim.render.bench_surface:bench_native"),
    "simulate_warm_s": bench_simulate,
    "haptic_loop_period_p99_ms": bench_haptic_loop,
    "haptic_loop_period_p99_ms_rendering": bench_haptic_loop_rendering,
    "render_update_1000_ms": bench_render,
    "first_frame_s": bench_render,
    **_by_name("render_fps_1024x768", "bonesim.render.bench:bench_fps"),
    "audio_rtf_p99": bench_audio,
    "dust_step_64_ms": bench_dust,
    "recording_overhead_us": bench_recording,
    "recording_writer_rows_per_s": bench_recording,
    **_by_name("session_bytes_per_minute", "bonesim.bench.record:bench_session_size"),
    "tutor_loopback_latency_p99_ms": bench_tutor,
    "tutor_loopback_latency_p50_ms": bench_tutor,
    "tutor_loopback_loss_fraction": bench_tutor,
    "monitor_update_us": bench_monitor,
    "monitor_loopback_latency_p99_ms": bench_monitor,
    "monitor_loopback_loss_fraction": bench_monitor,
    "load_labelstack_512_s": bench_load,
    "load_labelstack_512_peak_mb": bench_load,
    **_by_name(("load_native_256_s", "load_native_256_peak_mb", "load_native_512_s",
                "load_native_512_peak_mb"), "bonesim.bench.load:bench_load_native"),
    **_by_name("dp_align_1000_ms", "metrics.bench.alignment:bench_dp_align"),
    **_by_name("visibility_offline_removals_per_s",
               "metrics.bench.visibility:bench_metrics_visibility"),
    **_by_name("assess_run_s", "metrics.bench.assessment:bench_assess_run"),
    **_by_name(("cohort_sessions_per_s", "cohort_stats_s", "metrics_run_s"),
               "metrics.bench.cohort:bench_metrics_cohort"),
    **_by_name(("fragment_local_ms", "fragment_global_256_ms", "fragment_global_256_scipy_ms",
                "fragment_global_vs_scipy", "fragment_split_8000_ms"),
               "bonesim.bench.fragments:bench_fragments"),
    **_by_name(tuple(f"device_overhead_us_{b}" for b in (
        "simulated_hand", "spacemouse", "pedal", "adu100_handle", "touch")),
        "bonesim.bench.devices:bench_devices"),
    **_by_name(("dataset_frames_per_s_640x480", "dataset_vs_playback_video_fps"),
               "bonesim.bench.dataset:bench_dataset"),
    **_by_name("cut_plane_stroke_ms", "bonesim.bench.cut_irrigation:bench_cut_plane"),
    **_by_name("dust_irrigated_step_64_ms", "bonesim.bench.cut_irrigation:bench_irrigated_dust"),
    # the loop's period while a fragment moves, and still, in one run
    **_by_name(("haptic_loop_period_fragment_p99_ms", "haptic_loop_period_still_p99_ms"),
               "bonesim.bench.rigid:bench_rigid_loop"),
    # the loop's period while a 512k-voxel part splits off, a stroke cuts, a burr changes
    **_by_name(tuple(f"haptic_loop_period_{w}" for w in (
        "split_512k_p99_ms", "split_512k_max_ms", "cut_stroke_p99_ms", "burr_change_p99_ms",
        "grab_512k_p99_ms", "quiet_p99_ms")), "bonesim.bench.stalls:bench_stalls"),
    **_by_name("tutor_tracking_vs_ideal", "bonesim.bench.tutor_tracking:bench_tutor_tracking"),
    **_by_name("main_job_s", "bonesim.bench.tutor_tracking:bench_main_job"),
}
#: Entries that take minutes: run only when named (``--only NAME``).
ON_REQUEST = ("main_job_s",)


def run_benchmarks(only=None, quick=False) -> dict:
    """Run the named benchmarks (by default all but the :data:`ON_REQUEST`
    ones) and return their figures."""
    from bonesim.errors import BonesimError

    names = [n for n in BENCHMARKS if n not in ON_REQUEST] if not only else list(only)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise BonesimError(f"unknown benchmark(s) {unknown}; known: {list(BENCHMARKS)}",
                           field="--only")
    results: dict = {}
    done = set()
    for name in names:
        fn = BENCHMARKS[name]
        if fn in done:
            continue
        done.add(fn)
        for k, v in fn(quick=quick).items():
            if k in names or (not only and k not in ON_REQUEST):
                results[k] = v
    machine = {"cpus": os.cpu_count(), "python": sys.version.split()[0],
               "quick": bool(quick)}
    for v in results.values():
        v["machine"] = machine
    return results
