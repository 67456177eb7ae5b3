"""Stretches of the phantom's demo plan for tests that need a run that cuts
bone from its first steps."""
from __future__ import annotations

import functools

import numpy as np

from bonesim.io.case import load_case
from bonesim.io.toolpath import demo_trajectory


@functools.lru_cache(maxsize=4)
def phantom_demo(burr: str = "cutting-5mm"):
    """The phantom's one-burr demo plan (planned once per process)."""
    return demo_trajectory(load_case("phantom"), burr)


def first_cut(traj, case=None) -> int:
    """Index of the first drilling sample whose burr centre lies in bone (the
    plan's first passes only graze the cortex's highest points)."""
    case = load_case("phantom") if case is None else case
    vol = case.load_volume()
    kinds = np.array(["none"] + [s.kind for s in case.structures])
    bone = (kinds == "bone")[vol.labels]
    ijk = np.rint((traj.pos_mm - vol.origin_mm) / vol.spacing_mm).astype(int)
    inside = np.all((ijk >= 0) & (ijk < vol.shape), axis=1)
    hit = np.zeros(len(ijk), bool)
    hit[inside] = bone[tuple(ijk[inside].T)]
    q = np.flatnonzero(hit & traj.drill.astype(bool))
    if not len(q):
        raise ValueError("the trajectory never drills inside the bone")
    return int(q[0])


def drilling_window(burr: str = "cutting-5mm", samples: int = 3000, lead_s: float = 0.1):
    """``samples`` points of the phantom's demo plan from ``lead_s`` before
    (negative: after) its burr first drills inside the bone (a Trajectory at
    the plan's rate; ``.resample(1000.0)`` for haptic steps)."""
    traj = phantom_demo(burr)
    start = int(np.searchsorted(traj.t_s, traj.t_s[first_cut(traj)] - lead_s))
    return traj.at_times(traj.t_s[start:start + samples])
