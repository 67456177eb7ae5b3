"""Benchmark of loading a big label stack (:mod:`bonesim.io.label_stack`).

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

__all__ = ["SHAPE", "QUICK_SHAPE", "ORIENTATION", "REPEATS", "write_stack_case",
           "bench_load"]

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


def write_stack_case(folder: Path, shape_img=SHAPE, code: str = ORIENTATION) -> Path:
    """Write a label-stack case of ``shape_img`` (columns, rows, slices).

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
             f'orientation = "{code}"', f'size_mm = {size_img}', '']
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


if __name__ == "__main__":
    _child(sys.argv[1])
