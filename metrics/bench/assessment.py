"""Benchmark of the final-product assessment (:mod:`metrics.assessment`).

``assess_run_s``
    Seconds of :func:`metrics.assessment.assess_session` on one 3-minute
    synthetic expert-like run of the phantom (:func:`metrics.synth.synth_cohort`;
    1 minute with ``quick``), warm (the second call): the session read from
    the file, its case's model rebuilt, the tissue at the end rebuilt from
    the removals, every item measured and scored, as ``bonesim assess`` does
    it without ``--png``. The detail splits it: ``read_s`` (the file),
    ``model_s`` (the model rebuild) and ``measure_s`` (the measurements and
    scores, :func:`~metrics.assessment.assess_tissue`), and gives the run's
    score.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

__all__ = ["bench_assess_run"]


def bench_assess_run(quick=False) -> dict:
    """The figure of the module docstring."""
    from bonesim.session.reader import read_session
    from metrics.assessment import assess_session, assess_tissue, final_present
    from metrics.synth import synth_cohort

    dur = 60.0 if quick else 180.0
    with tempfile.TemporaryDirectory() as tmp:
        (path,) = synth_cohort(Path(tmp) / "one", 1, 0, seed=1, duration_s=dur)
        t0 = time.perf_counter()
        assess_session(path)
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        a = assess_session(path)
        warm = time.perf_counter() - t0
        t0 = time.perf_counter()
        s = read_session(path)
        read_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = s.load_model()
    model_s = time.perf_counter() - t0
    d0, lab0 = model.grid.to_dense()
    present = final_present(s, model)
    case = model.case
    t0 = time.perf_counter()
    assess_tissue(lab0, present, model.spacing_mm, model.grid.origin_mm, model.structures,
                  case.landmarks, case.camera.eye_mm, density0=d0)
    measure_s = time.perf_counter() - t0
    return {"assess_run_s": {
        "value": round(warm, 3), "unit": "s", "run_s": dur,
        "removed_mm3": round(a.removed_mm3, 1), "score": f"{a.total}/{a.max_total}",
        "read_s": round(read_s, 3), "model_s": round(model_s, 3),
        "measure_s": round(measure_s, 3), "first_call_s": round(cold, 3)}}
