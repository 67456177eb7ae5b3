"""Building a :class:`~bonesim.engine.model.Model` from files: a case and a burr
on disk (:func:`load_model`), or the small warm-up slab on which the kernels
compile (:func:`warmup_model`, :func:`warmup`).

This sits on the file side of the engine: the engine itself (:mod:`bonesim.engine.model`)
builds a model from arrays and reads no case, burr or clearance file.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from bonesim.engine.bodies import publish_split_box, set_pose, split_body
from bonesim.io.burrs import load_burr
from bonesim.io.limits import check_burr_lattice
from bonesim.physics.clearance import Clearance
from bonesim.engine.device_caps import SCRIPTED, DeviceCaps
from bonesim.engine.haptics_rows import ROWS_MIN_OVERSAMPLE
from bonesim.engine.model import (DEFAULT_OVERSAMPLE, Model, Sample, clear_touched, make_model, make_state,
                                  step)

__all__ = ["load_model", "warmup_model", "warmup_sample", "warmup"]


def load_model(case="phantom", burr: str = "cutting-5mm", *,
               device: DeviceCaps = SCRIPTED, oversample: int = DEFAULT_OVERSAMPLE,
               materials: dict | None = None, voxel_mm: float | str | None = None
               ) -> Model:
    """Load a case and a burr from their files and build the model.

    Parameters
    ----------
    case : str, Path or Case
        Bundled case name, path of a ``case.toml``, or a loaded case.
    burr : str
        Burr name (``cutting-5mm``) or path of a burr file.
    device : DeviceCaps
        The device's limits.
    oversample : int
        Burr lattice refinement.
    materials : dict, optional
        Kind -> material (default: the bundled materials).
    voxel_mm : float or "native", optional
        Overrides the case's ``[volume] voxel_mm`` (see
        :meth:`bonesim.io.case.Case.with_voxel_mm`).

    Notes
    -----
    At ``voxel_mm = "native"`` on an isotropic source the engine's grid is
    the source's grid: the case volume holds one label array, and the
    clearance field is built from it (no second copy).
    """
    from bonesim.io.case import load_case

    c = load_case(case, voxel_mm=voxel_mm)
    b = load_burr(burr) if isinstance(burr, str) else burr
    vol = c.load_volume()
    # display colours settled on this volume (neighbours apart); the case keeps
    # the view derived from it, so nothing reads the volume twice
    c = c.resolved(vol)
    check_burr_lattice(b.diameter_mm, float(vol.spacing_mm), oversample, b.source)
    model = make_model(vol.labels, vol.spacing_mm, c.structures, b,
                       origin_mm=vol.origin_mm, materials=materials, device=device,
                       oversample=oversample, name=c.name, case=c)
    danger = [s for s, st in enumerate(c.structures, start=1) if st.kind != "bone"]
    return replace(model, clearance=Clearance.from_native(vol.native_labels, danger))


def warmup_model(oversample: int = DEFAULT_OVERSAMPLE, burr=None,
                 voxel_mm: float = 0.5) -> Model:
    """A 12³ slab of bone (0.5 mm voxels unless ``voxel_mm`` says, ``burr``
    or else the shipped 1 mm cutting burr) on which the warm-ups compile
    kernels for a real model's array types."""
    from types import SimpleNamespace

    labels = np.zeros((12, 12, 12), dtype=np.uint8)
    labels[:, :, :6] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(255, 255, 255))
    burr = load_burr("cutting-1mm") if burr is None else burr
    return make_model(labels, voxel_mm, [bone], burr, oversample=oversample)


def warmup_sample(model: Model) -> Sample:
    """A sample of the running drill just under the warm-up slab's top."""
    return Sample(0.0, np.array([3.0, 3.0, 2.9]), np.array([0.0, 0.0, -1.0]),
                  True, model.burr.default_speed_rpm, 1)


def warmup(burr=None) -> None:
    """Compile every kernel :func:`bonesim.engine.model.step` uses (cached on
    disk after the first run); ``burr``: as :func:`warmup_model` (a recorded
    run's own burr needs no burr file)."""
    m = warmup_model(burr=burr)
    s = make_state(m)
    step(m, s, warmup_sample(m))
    clear_touched(s, s.touched.read(0)["ijk"])
    split_body(s, 0, np.array([[0, 0, 0]]))           # a second body: the split kernels
    publish_split_box(s, 0, (0, 0, 0), (1, 1, 1), 0.0)
    from bonesim.engine.fragments import publish_part       # the fragment finder's commands

    publish_part(s, 0, (3, 3, 0), (3, 3, 0), (3, 3, 0), 1, 0.0)
    publish_part(s, 0, (4, 4, 0), (4, 4, 0), (4, 4, 0), 1, 0.0, shed=True)
    from bonesim.engine.slicing import TABLES, voxels_per_step
    from bonesim.engine.split_jobs import run_split            # a large split's slices

    for table in TABLES:                               # the slice sizes read once, now
        voxels_per_step(table)
    run_split(s, 0, (6, 6, 0), (6, 6, 0), (7, 7, 1), 8, 0.0, budget=2)
    from bonesim.engine.cut_plane import advance_cuts, plane_pose, publish_cut, queue_cut

    pose = plane_pose((3.0, 3.0, 4.0), (0.0, 0.0, -1.0))      # a stroke, at once and sliced
    publish_cut(s, m.injury, pose, 1.0, 1.0, 1.0, 0.0)
    queue_cut(s, m.injury, np.array([1000, 1000, 1000]), pose, 0.0, 2)
    while s.cut_jobs:
        advance_cuts(s, 0.0)
    set_pose(s, 1, (0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0))  # bodies apart: several passes
    step(m, s, warmup_sample(m)._replace(t_s=0.001))
    step(m, s, warmup_sample(m)._replace(t_s=0.002, pos_mm=np.array([0.2, 0.2, 1.0])))
    # the row kernel of fine stencils (the budget binds below voxel / oversample
    # = 0.25 mm, so a slab of 1 mm voxels)
    m4 = warmup_model(ROWS_MIN_OVERSAMPLE + 1, burr, voxel_mm=1.0)
    step(m4, make_state(m4), warmup_sample(m4))
    # the fixed-budget step of bone finer than its lattice (native resolution),
    # with its carried removal flushed on a later step
    mb = warmup_model(burr=burr, voxel_mm=0.5 / 8)
    sb = make_state(mb)
    smp = warmup_sample(mb)._replace(pos_mm=np.array([0.375, 0.375, 0.36]))
    step(mb, sb, smp)
    step(mb, sb, smp._replace(t_s=0.001, drill=False))
