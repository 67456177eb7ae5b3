"""Benchmarks of loading big label stacks (:mod:`bonesim.io.label_stack`).

``load_labelstack_512_s``: wall time of :meth:`bonesim.io.case.Case.load_volume`
on a 512 x 512 x 500 label-stack case (the phantom's anatomy upsampled to
about 0.1 mm pixels, RGB PNG slices, declared ``"PIR"``: permuted and
flipped as real exports are), measured in a fresh process.
``load_labelstack_512_peak_mb``: that process's peak resident memory [MB]
(Linux ``VmHWM``, interpreter and imports included; the figure reports
the part before loading too). The reference measured in the same run is a
plain serial decode of the same PNG files with Pillow (each slice read into
an array and dropped): the load's ratio to it says how much the labelling,
reorientation and resampling cost over the decode alone.

The stack is written once per run into a temporary folder (not timed).

``load_native_256_s`` / ``_peak_mb`` and ``load_native_512_s`` / ``_peak_mb``
(:func:`bench_load_native`): a 256³ and a 512³ stack loaded at
``voxel_mm = "native"`` (the engine's grid is the stack's), through the
engine's model and the clearance field, with each part's time and peak.
"""
from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["SHAPE", "QUICK_SHAPE", "ORIENTATION", "REPEATS", "NATIVE_SIZES",
           "QUICK_NATIVE_SIZES", "NATIVE_REPEATS", "write_stack_case", "bench_load",
           "bench_load_native"]

#: Stack size: image columns, rows, slices.
SHAPE = (512, 512, 500)
#: Quick mode's stack (CI smoke test of the benchmark itself).
QUICK_SHAPE = (128, 128, 120)
#: Orientation code the stack is written and declared in.
ORIENTATION = "PIR"
#: Load repeats (the median is reported).
REPEATS = 3


def _upsampled_labels(shape_img, code: str):
    """The phantom's labels on a fine grid of ``shape_img`` image voxels."""
    from bonesim.io.orientation import axis_map
    from bonesim.io.phantom import PARTS, phantom_volume
    from bonesim.io.volumes import nearest_indices

    vol = phantom_volume(voxel_mm=0.5)
    source, _ = axis_map(code)
    shape_lps = [shape_img[source[a]] for a in range(3)]
    spacing = vol.extent_mm / np.asarray(shape_lps, float)
    out = vol.labels
    for a in range(3):
        idx = nearest_indices(vol.shape[a], vol.spacing_mm, spacing[a], shape_lps[a])
        out = np.take(out, idx, axis=a)
    return out, vol.extent_mm, PARTS


def write_stack_case(folder: Path, shape_img=SHAPE, code: str = ORIENTATION, *,
                     voxel_mm: float | str | None = None, camera: bool = False) -> Path:
    """Write a label-stack case of ``shape_img`` (columns, rows, slices).

    Parameters
    ----------
    folder : Path
        Receives ``slices/`` and ``case.toml``.
    shape_img : (3,) int
        Image columns, rows and slices.
    code : str
        Orientation code the slices are written and declared in.
    voxel_mm : float or "native", optional
        The manifest's ``voxel_mm`` (default: left out, 0.5 mm).
    camera : bool
        Declare a ``[camera]`` (the phantom's lateral view), so that loading
        the volume derives no view from the anatomy.

    Returns
    -------
    Path
        Its ``case.toml``.
    """
    from bonesim.io.label_stack import write_label_stack
    from bonesim.io.orientation import axis_map

    labels, extent, names = _upsampled_labels(shape_img, code)
    rng = np.random.default_rng(7)
    colors = [tuple(int(v) for v in c) for c in
              rng.choice(np.arange(40, 250), size=(len(names), 3), replace=True)]
    write_label_stack(folder / "slices", labels, colors, orientation=code)
    source, _ = axis_map(code)
    size_img = [0.0, 0.0, 0.0]
    for a in range(3):
        size_img[source[a]] = float(extent[a])
    kinds = {"bone": "bone", "sigmoid_sinus": "soft", "posterior_fossa_dura": "soft",
             "middle_fossa_dura": "soft"}
    lines = ['[case]', 'name = "bench_stack"', 'side = "left"', '', '[volume]',
             'format = "label-stack"', 'path = "slices"', 'pattern = "plane*.png"',
             f'orientation = "{code}"', f'size_mm = {size_img}']
    if voxel_mm is not None:
        lines.append(f"voxel_mm = {json.dumps(voxel_mm)}")
    lines.append('')
    if camera:
        lines += ['[camera]', 'eye_mm = [120.0, 0.0, 0.0]', 'focal_mm = [20.0, 0.0, 0.0]',
                  'up = [0.0, 0.0, 1.0]', '']
    for n, c in zip(names, colors):
        lines += ['[[structures]]', f'name = "{n}"',
                  f'kind = "{kinds.get(n, "critical")}"', f'color = {list(c)}', '']
    manifest = folder / "case.toml"
    manifest.write_text("\n".join(lines))
    return manifest


def _peak_rss_mb() -> float:
    """This process's peak resident memory [MB] (``VmHWM``; ``ru_maxrss`` would
    carry the parent's peak across fork and exec)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _child(folder: str) -> None:
    """Load the case once in this process; print seconds and memory as JSON."""
    from bonesim.io.case import load_case

    case = load_case(folder)
    base = _peak_rss_mb()
    t0 = time.perf_counter()
    vol = case.load_volume()
    wall = time.perf_counter() - t0
    peak = _peak_rss_mb()
    print(json.dumps({"s": wall, "peak_mb": peak, "base_mb": base,
                      "grid": list(vol.shape), "native": list(vol.native_labels.labels.shape),
                      "bone_voxels": int(np.count_nonzero(vol.labels == 1))}))


def _plain_decode_s(folder: Path) -> float:
    from PIL import Image

    t0 = time.perf_counter()
    for f in sorted((folder / "slices").glob("plane*.png")):
        with Image.open(f) as im:
            np.asarray(im)
    return time.perf_counter() - t0


def bench_load(quick=False) -> dict:
    """Load a 512 x 512 x 500 label stack: wall time and peak memory."""
    shape = QUICK_SHAPE if quick else SHAPE
    runs = []
    with tempfile.TemporaryDirectory(prefix="bonesim-bench-stack-") as tmp:
        folder = Path(tmp)
        write_stack_case(folder, shape)
        cmd = [sys.executable, "-m", "bonesim.bench.load", str(folder)]
        for _ in range(1 if quick else REPEATS):
            res = subprocess.run(cmd, check=True, capture_output=True, text=True)
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        decode = min(_plain_decode_s(folder) for _ in range(1 if quick else 2))
    wall = float(np.median([r["s"] for r in runs]))
    peak = max(r["peak_mb"] for r in runs)
    first = runs[0]
    common = {"stack": list(shape), "orientation": ORIENTATION,
              "native": first["native"], "grid": first["grid"]}
    return {
        "load_labelstack_512_s": {
            "value": round(wall, 3), "unit": "s", **common,
            "reference": "plain serial Pillow decode of the same PNGs",
            "reference_s": round(decode, 3),
            "ratio_load_over_decode": round(wall / decode, 3),
            "runs": len(runs)},
        "load_labelstack_512_peak_mb": {
            "value": round(peak, 1), "unit": "MB", **common,
            "before_load_mb": round(first["base_mb"], 1),
            "labels_native_mb": round(float(np.prod(shape)) / 2**20, 1)},
    }


# ------------------------------------------------------ native resolution
def _reset_peak() -> bool:
    """Restart this process's peak-RSS mark (Linux ``clear_refs``); False
    where the system does not allow it (the parts' peaks then include the
    earlier parts')."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _native_child(folder: str) -> None:
    """Load a native-resolution case once, part by part, in this process;
    print seconds and memory as JSON.

    The parts are what :func:`bonesim.io.loading.load_model` does for a case
    with a ``[camera]`` and settled colours: read the stack into case-frame
    labels on the engine's grid (``read``), build the engine's brick grid
    (``model``: :func:`bonesim.engine.model.make_model`) and the clearance
    field on the source-resolution labels (``clearance``).
    """
    from bonesim.engine.model import make_model
    from bonesim.io.burrs import load_burr
    from bonesim.io.case import load_case
    from bonesim.physics.clearance import Clearance

    case = load_case(folder)
    burr = load_burr("cutting-5mm")
    base = _peak_rss_mb()
    parts: dict = {}
    exact = True

    def part(name, fn):
        nonlocal exact
        exact = _reset_peak() and exact
        t0 = time.perf_counter()
        out = fn()
        parts[name] = {"s": time.perf_counter() - t0, "peak_mb": _peak_rss_mb()}
        return out

    t0 = time.perf_counter()
    vol = part("read", case.load_volume)
    model = part("model", lambda: make_model(vol.labels, vol.spacing_mm, case.structures,
                                             burr, origin_mm=vol.origin_mm, case=case))
    danger = [s for s, st in enumerate(case.structures, start=1) if st.kind != "bone"]
    clear = part("clearance", lambda: Clearance.from_native(vol.native_labels, danger))
    wall = time.perf_counter() - t0
    print(json.dumps({"s": wall, "peak_mb": max(p["peak_mb"] for p in parts.values()),
                      "base_mb": base, "parts": parts, "exact_parts": exact,
                      "grid": list(vol.shape), "voxel_mm": vol.spacing_mm,
                      "one_label_array": vol.native is None,
                      "grid_mb": model.grid.nbytes / 2**20,
                      "clearance_mb": clear.nbytes / 2**20}))


#: Native stacks (cubes of this many voxels a side) and their quick sizes.
NATIVE_SIZES = {"256": 256, "512": 512}
QUICK_NATIVE_SIZES = {"256": 48, "512": 64}
#: Load repeats per native stack (the median is reported; peaks are the max).
NATIVE_REPEATS = {"256": 3, "512": 2}


def bench_load_native(quick=False) -> dict:
    """Load 256³ and 512³ label stacks at ``voxel_mm = "native"``: wall
    time and peak memory, each part's share.

    The stacks are the phantom's anatomy upsampled onto cubes (52 mm across:
    0.203 mm and 0.102 mm pixels, as real segmentations' 0.1-0.2 mm), RGB PNG
    slices declared ``"PIR"``, with a ``[camera]`` (no view is derived;
    the landmarks and the side and orientation check, which every load
    derives, are part of the figure, the colours' neighbours are not),
    written once per run into a temporary folder (not timed). Each load runs
    in a fresh process (numba's cached kernels load there too).
    """
    sizes = QUICK_NATIVE_SIZES if quick else NATIVE_SIZES
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="bonesim-bench-native-") as tmp:
        for key, n in sizes.items():
            folder = Path(tmp) / key
            write_stack_case(folder, (n, n, n), voxel_mm="native", camera=True)
            cmd = [sys.executable, "-m", "bonesim.bench.load", "--native", str(folder)]
            runs = []
            for _ in range(1 if quick else NATIVE_REPEATS[key]):
                res = subprocess.run(cmd, check=True, capture_output=True, text=True)
                runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
            first = runs[0]
            parts = {name: {"s": round(float(np.median([r["parts"][name]["s"] for r in runs])),
                                       3),
                            "peak_mb": round(max(r["parts"][name]["peak_mb"] for r in runs), 1)}
                     for name in first["parts"]}
            common = {"stack": [n, n, n], "orientation": ORIENTATION,
                      "grid": first["grid"], "voxel_mm": round(first["voxel_mm"], 6),
                      "one_label_array": first["one_label_array"], "parts": parts,
                      "runs": len(runs)}
            out[f"load_native_{key}_s"] = {
                "value": round(float(np.median([r["s"] for r in runs])), 3), "unit": "s",
                **common, "limit_s": 5.0 if key == "256" else 20.0}
            out[f"load_native_{key}_peak_mb"] = {
                "value": round(max(r["peak_mb"] for r in runs), 1), "unit": "MB", **common,
                "limit_mb": 1024.0 if key == "256" else 3072.0,
                "before_load_mb": round(first["base_mb"], 1),
                "parts_exact": all(r["exact_parts"] for r in runs),
                "labels_mb": round(n ** 3 / 2**20, 1),
                "grid_mb": round(first["grid_mb"], 1),
                "clearance_mb": round(first["clearance_mb"], 1)}
    return out


if __name__ == "__main__":
    if sys.argv[1] == "--native":
        _native_child(sys.argv[2])
    else:
        _child(sys.argv[1])
