"""Short recordings of the phantom's planned demo for the dataset and export
tests (a few seconds of drilling; recorded once per test session through
``tests/bonesim/conftest.py``)."""
from __future__ import annotations

import numpy as np

__all__ = ["demo_part", "record"]


def demo_part(first_s: float, seconds: float):
    """The demo mastoidectomy's trajectory from ``first_s`` seconds after its
    first drilling sample, ``seconds`` long (a Trajectory)."""
    from bonesim.io.case import load_case
    from bonesim.io.toolpath import demo_trajectory

    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    dt = float(t.t_s[1] - t.t_s[0])
    a = start + int(round(first_s / dt))
    b = a + int(round(seconds / dt))
    return t.at_times(t.t_s[a:b])


def record(path, traj, case="phantom"):
    """Drill ``traj`` into ``case`` headless and record it to ``path``."""
    from bonesim.io.loading import load_model
    from bonesim.runtime.simulate import run_trajectory

    run_trajectory(load_model(case, "cutting-5mm"), traj, surface=False, record=path)
    return path
