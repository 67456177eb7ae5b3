"""Headless runs: a scripted trajectory through the haptic step at 1 kHz.

:func:`run_trajectory` is what ``bonesim simulate`` does. The trajectory is
resampled at the model's haptic rate (simulated time, not wall-clock) and fed
sample by sample to :func:`bonesim.engine.world.world_step`, exactly as the
haptic loop feeds device samples: burr changes (the trajectory's ``burr``
column) and any world commands given with their times
(:mod:`bonesim.engine.world_commands`: splits, grabs, plates...) are applied
before the step of their time, and fragments and plates in motion move
(fall under gravity and rest, follow a grabbing tool) as in the loop. A
:class:`~bonesim.engine.replica.TissueReplica` drains the tissue-event and
touched rings at the frame rate and updates the hybrid surface
incrementally, as the window does. The haptic step never waits for
it.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.engine.haptics import O_N_IMMERSED
from bonesim.engine.model import Model, Sample, make_state, step
from bonesim.engine.replica import TissueReplica
from bonesim.engine.world import world_step
from bonesim.engine.world_commands import SetBurr
from bonesim.io.anatomy import clinical_name

__all__ = ["FRAME_HZ", "CLEARANCE_EVERY", "warmup", "run_trajectory", "closest_approach",
           "approach_text"]

#: Frame rate at which the surface consumer drains the rings [Hz].
FRAME_HZ = 60.0

#: The drilling burr's closest approach to a structure is checked every this
#: many haptic steps (5 ms at 1 kHz: under 0.1 mm of travel at drilling speed).
CLEARANCE_EVERY = 5


def warmup() -> None:
    """Compile the consumer's kernels for the array types of a real run: its
    replica shares the model's read-only labels, which the surface's own
    warm-up grid does not have (the first ``bonesim run`` after set-up
    compiled them at start, about 2 s)."""
    from bonesim.io.loading import warmup_model, warmup_sample

    m = warmup_model()
    s = make_state(m)
    consumer = TissueReplica(m, s, surface=True)
    step(m, s, warmup_sample(m))
    ch = consumer.drain()
    if len(ch.removed) + len(ch.touched) == 0:
        raise RuntimeError("surface consumer warm-up: the step published nothing to drain")
    ev = events.empty_events(1)                 # a removal through the replica itself
    ev["ijk"][0] = (6, 6, 5)
    consumer.apply(ev)


def run_trajectory(model: Model, traj, *, check: bool = False, out_dir=None,
                   mesh_format: str = "ply", surface: bool = True,
                   progress=None, record=None, header: dict | None = None,
                   burrs=(), commands=()) -> dict:
    """Drill ``traj`` into ``model`` and summarize the run.

    Parameters
    ----------
    model : Model
    traj : bonesim.io.trajectory.Trajectory
        Case-frame tool path.
    check : bool
        Compare the incrementally updated surface with a from-scratch
        tessellation of the final grid and report ``surface_consistent``.
    out_dir : path, optional
        Where to write the final mesh (``surface.ply`` or ``.vtp``) and
        ``summary.json``.
    mesh_format : {"ply", "vtp"}
    surface : bool
        Maintain the surface (False: haptics only, for benchmarks).
    progress : callable, optional
        Called with the fraction done now and then.
    record : path, optional
        Record the run to this new session file (:mod:`bonesim.runtime.record`);
        a run whose estimated file would not fit is refused first
        (:func:`bonesim.session.disk_guard.check_space`). If recording stops
        early (a full disk), the run goes on and the summary says so.
    header : dict, optional
        The recording's header (default :func:`bonesim.session.header.make_header`
        of ``model`` and ``burrs``).
    burrs : sequence of Burr
        Burrs 1, 2, ... the trajectory's ``burr`` column may switch to (0 is
        the model's); each switch is a burr change in the tissue events, as
        the haptic loop publishes one.
    commands : sequence of (t_s, WorldCommand)
        World commands (:mod:`bonesim.engine.world_commands`) applied before
        the first step at or after ``t_s`` [s], in the order given (times
        non-decreasing), after that step's burr change.

    Returns
    -------
    dict
        JSON-ready summary (see ``bonesim simulate --help``); with ``record``,
        also ``record``, ``record_ok``, ``record_kept`` and ``record_error``.
    """
    wall0 = time.perf_counter()
    rate = model.haptic_rate_hz
    commands = list(commands)
    if any(b[0] < a[0] for a, b in zip(commands, commands[1:])):
        raise ValueError("simulate: the commands' times must not decrease")
    samples = traj.resample(rate)
    burrs = list(burrs)
    if int(samples.burr.max()) > len(burrs):
        raise ValueError(f"the trajectory uses burr {int(samples.burr.max())}; the run has "
                         f"burrs 0..{len(burrs)}")
    if record is not None:         # room for the file? (refused with the estimate)
        from bonesim.session import disk_guard

        disk_guard.check_space(record, float(samples.t_s[-1] - samples.t_s[0]), rate)
    if header is None and record is not None:
        from bonesim.session.header import make_header

        header = make_header(model, burrs, input_device="scripted")
    if burrs:
        model = model.with_burrs(burrs)
    state = make_state(model)
    consumer = TissueReplica(model, state, surface=True) if surface else None
    injuries = []
    n = len(samples.t_s)
    frame_every = max(int(round(rate / FRAME_HZ)), 1)
    step_ns = np.zeros(n, dtype=np.int64)
    force = np.zeros(n)
    contact = np.zeros(n, dtype=bool)
    perf = time.perf_counter_ns
    pos, axis = samples.pos_mm, samples.axis
    rec = _Recording(model, state, record, header) if record is not None else None
    burr = samples.burr
    t_col = samples.t_s
    c = 0
    none = ()
    try:
        for q in range(n):
            cmds = none
            if burr[q] != state.burr or (c < len(commands) and commands[c][0] <= t_col[q]):
                cmds = [SetBurr(int(burr[q]))] if burr[q] != state.burr else []
                while c < len(commands) and commands[c][0] <= t_col[q]:
                    cmds.append(commands[c][1])
                    c += 1
            smp = Sample(t_col[q], pos[q], axis[q], bool(samples.drill[q]),
                         float(samples.speed_rpm[q]), int(samples.direction[q]),
                         int(burr[q]))
            t0 = perf()
            f = world_step(model, state, smp, cmds)
            step_ns[q] = perf() - t0
            if rec is not None:
                rec.push(smp, f)
            force[q] = np.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
            contact[q] = state.out[O_N_IMMERSED] > 0
            if consumer is not None and q % frame_every == frame_every - 1:
                injuries.append(consumer.drain().injuries)
            if progress is not None and q % 5000 == 0:
                progress(q / n)
    except BaseException:
        if rec is not None:                # keep what was recorded, then fail
            rec.close()
        raise
    if consumer is not None:
        injuries.append(consumer.drain().injuries)
    else:
        injuries.append(events.injuries(state.tissue.read(max(0, state.tissue.count
                                                                  - state.tissue.capacity))))
    summary = _summary(model, state, step_ns, force, contact, consumer, injuries)
    every = np.arange(0, n, CLEARANCE_EVERY)
    drilling = every[samples.drill[every].astype(bool)]
    radii = np.array([b.radius_mm for b in model.burrs])[samples.burr[drilling]]
    gap, label, at = closest_approach(model, pos[drilling], radii)
    if at >= 0:
        name = model.structure_name(label)
        summary["closest_approach"] = {
            "clearance_mm": round(gap, 3), "structure": name,
            "display_name": clinical_name(name),
            "t_s": round(float(samples.t_s[drilling[at]]), 3),
            "native_spacing_mm": [round(float(v), 4) for v in model.clearance.spacing_mm]}
    if rec is not None:
        summary.update(rec.close())
    if check and consumer is not None:
        from bonesim.engine.surface import Surface

        fresh = Surface.of_model(model, state.grid)
        summary["surface_consistent"] = bool(_same_surface(fresh, consumer.surface))
    if out_dir is not None and consumer is not None:
        from bonesim.io.meshes import write_mesh

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        mesh = out / f"surface.{mesh_format}"
        p, nrm, col, tri = consumer.surface.arrays()
        write_mesh(mesh, p, tri, nrm=nrm, col=col)
        summary["mesh"] = str(mesh)
        summary["summary"] = str(out / "summary.json")
    summary["wall_s"] = round(time.perf_counter() - wall0, 3)
    if out_dir is not None and consumer is not None:
        from bonesim import __version__

        Path(summary["summary"]).write_text(json.dumps(
            {"bonesim_version": __version__, **summary}, indent=2) + "\n")
    return summary


class _Recording:
    """Feeds a session file from an in-process run (the haptic loop's
    ``samples`` ring plus the state's rings, drained every half ring;
    ``handle``: an instrumented handle whose angles are recorded as the loop
    records them, :mod:`bonesim.runtime.handle_stream`)."""

    def __init__(self, model, state, path, header, handle=None):
        from bonesim.runtime.record import Drainer
        from bonesim.session.writer import SessionWriter
        from bonesim.session.header import make_header, recorded_volume

        self.state = state
        self.ring = events.Ring.create(1 << 12, **events.OTHER_RINGS["samples"][1])
        header = make_header(model, input_device="scripted") if header is None else header
        self.writer = SessionWriter(path, header, volume=recorded_volume(model, header))
        vis = None
        cam = getattr(getattr(model, "case", None), "camera", None)
        if cam is not None:                # judged from the case camera's eye
            from bonesim.physics.visibility import VisibilityTracker

            vis = VisibilityTracker([model] + [model.with_burr(b) for b in model.burrs[1:]],
                                    cam.eye_mm)
        rings = {"samples": self.ring, "tissue": state.tissue}
        self.tap = None
        if handle is not None:
            from bonesim.runtime.handle_stream import HandleTap

            rings["handle"] = events.Ring.create(1 << 12, **events.OTHER_RINGS["handle"][1])
            self.tap = HandleTap(rings["handle"], handle)
        self.drainer = Drainer(self.writer, rings, vis)
        self.zero = np.zeros(3)
        # the eye the removals are judged from, stored with the run (one row
        # at its first sample: a scripted run's view never moves)
        self.eye = cam

    def _log_eye(self, t_s: float) -> None:
        cam, self.eye = self.eye, None
        self.writer.append("camera", {"t_s": [t_s], "eye_mm": [cam.eye_mm],
                                      "focal_mm": [cam.focal_mm], "up": [cam.up]})

    def push(self, smp, f) -> None:
        from bonesim.runtime.haptic_loop import push_sample

        if self.writer.failed is not None:     # recording stopped: the run goes on
            return
        if self.eye is not None:
            self._log_eye(float(smp.t_s))
        push_sample(self.ring, smp.t_s, self.state, smp.pos_mm, smp.axis, smp.drill,
                    smp.speed_rpm, smp.direction, self.state.burr, self.state.epoch, 0, f,
                    self.zero)
        if self.tap is not None:
            self.tap(smp.t_s)
        if self.ring.count - self.drainer.cursors["samples"].pos >= self.ring.capacity // 2:
            self.drainer.drain()
            self.writer.flush()

    def close(self) -> dict:
        """Finish the file; returns ``record`` (its path), ``record_ok``,
        ``record_kept`` (see :attr:`SessionWriter.kept`) and ``record_error``
        (one line saying what was kept, or None)."""
        from bonesim.session.writer import kept_line

        if self.writer.failed is None:
            self.drainer.drain()
        self.writer.close()
        w = self.writer
        out = {"record": str(w.path), "record_ok": w.failed is None,
               "record_kept": dict(w.kept),
               "record_error": None if w.failed is None else kept_line(w.path, w.failed,
                                                                       w.kept)}
        if w.compact_error is not None:
            out["record_compact_error"] = w.compact_error
        return out


def _same_surface(a, b) -> bool:
    """Same vertices (position, normal, colour) and same oriented triangles."""
    return not a.canonical().differences(b.canonical())


def closest_approach(model: Model, pos_mm, radius_mm=None) -> tuple[float, int, int]:
    """The burr's closest approach to any structure that is not bone.

    Distances are exact at the case's native resolution
    (:class:`bonesim.physics.clearance.Clearance`, the model's ``clearance``).

    Parameters
    ----------
    model : Model
    pos_mm : (n, 3) float
        Burr centres, case frame [mm].
    radius_mm : float or (n,) float, optional
        The burr's radius at each point [mm] (default: the model's first
        burr's).

    Returns
    -------
    clearance_mm : float
        Smallest distance from the burr's sphere to a structure [mm]
        (negative: the sphere reaches into it; inf without points or field).
    label : int
        That structure's index (0 when none).
    index : int
        The point where it happens (-1 when none).
    """
    cl = model.clearance
    p = np.asarray(pos_mm, dtype=np.float64).reshape(-1, 3)
    if cl is None or not len(p) or not cl.structures:
        return float("inf"), 0, -1
    labels = list(cl.structures)
    r = model.burr.radius_mm if radius_mm is None else radius_mm
    d = cl.distances(p, [[s] for s in labels]) - np.broadcast_to(
        np.asarray(r, dtype=np.float64), (len(p),))[:, None]
    q, k = np.unravel_index(int(np.argmin(d)), d.shape)
    return float(d[q, k]), int(labels[k]), int(q)


def approach_text(clearance_mm: float, structure: str) -> str:
    """A distance line that names its structure by its clinical name:
    ``1.00 mm to the Facial nerve`` (``structure``: the code name).

    Parameters
    ----------
    clearance_mm : float
        Burr surface to the structure [mm] (negative: into it).
    structure : str
        The structure's name (as the case spells it).
    """
    return f"{clearance_mm:.2f} mm to the {clinical_name(structure)}"


def _summary(model, state, step_ns, force, contact, consumer, injuries) -> dict:
    names = [model.structure_name(s) for s in range(len(model.structures) + 1)]
    rem = {names[s]: int(c) for s, c in enumerate(state.removed_by_label) if s and c}
    inj = {k: np.concatenate([i[k] for i in injuries]) for k in injuries[0]}
    injuries = [{"structure": names[int(lab)], "kind": events.INJURY_KINDS[int(k)],
                 "t_s": round(float(t), 4),
                 "pos_mm": [round(float(x), 3) for x in p], "voxels": int(v)}
                for lab, k, t, p, v in zip(inj["label"], inj["kind"], inj["t_s"],
                                           inj["pos_mm"], inj["voxels"])]
    us = step_ns / 1e3
    out = {
        "case": model.name,
        "burr": getattr(model.burr, "name", "?"),
        "duration_s": round(float(state.t_s), 4) if len(step_ns) else 0.0,
        "steps": int(len(step_ns)),
        "voxels_removed": int(state.removed_by_label.sum()),
        "volume_removed_mm3": round(int(state.removed_by_label.sum()) * model.spacing_mm ** 3,
                                    3),
        "removed_by_structure": rem,
        "injuries": injuries,
        "force_n": {
            "mean": round(float(force.mean()), 4) if len(force) else 0.0,
            "mean_in_contact": round(float(force[contact].mean()), 4) if contact.any()
            else 0.0,
            "max": round(float(force.max()), 4) if len(force) else 0.0,
        },
        "haptic_step_us": {
            "p50": round(float(np.percentile(us, 50)), 2) if len(us) else 0.0,
            "p99": round(float(np.percentile(us, 99)), 2) if len(us) else 0.0,
        },
    }
    if consumer is not None:
        s = consumer.surface
        upd = np.array(consumer.update_s) * 1e3
        out["vertices"] = int(s.n_vertices)
        out["triangles"] = int(s.n_triangles)
        out["surface_update_ms"] = {
            "p50": round(float(np.percentile(upd, 50)), 3) if len(upd) else 0.0,
            "p99": round(float(np.percentile(upd, 99)), 3) if len(upd) else 0.0,
            "updates": int(len(upd)),
        }
    return out
