"""One world step: commands, rigid motion and the haptic step, in one place.

:func:`world_step` is what every run calls once per haptic sample: the
haptic loop (:mod:`bonesim.runtime.haptic_loop`), headless runs
(:func:`bonesim.runtime.simulate.run_trajectory`) and replay
(:mod:`bonesim.session.replay`). It

1. applies the commands given for this step (:mod:`bonesim.engine.world_commands`),
   in order, as state transitions at the sample's time, then one bounded
   slice of the queued large splits (:mod:`bonesim.engine.split_jobs`) and
   one of the queued large cut-plane strokes (:mod:`bonesim.engine.cut_plane`);
2. steps the rigid bodies (:meth:`bonesim.engine.rigid_set.RigidSet.advance`:
   the stopped tool pushes fragments, grabbed rigids follow it, everything
   in motion falls and rests; every pose change a ``POSE`` or ``PLATE``
   event), unless the state has no rigid set (``state.rigid`` None: a
   replay, whose recorded poses come as commands);
3. takes the haptic step (:func:`bonesim.engine.model.step`) with the
   state's current burr.

Everything it changes is in the :class:`~bonesim.engine.model.State`, so
the same model, the same samples and the same commands give the same
tissue events and forces, bit for bit, in any of those runs. Without
commands and without rigids in motion it is the haptic step plus a few
comparisons, and allocates nothing. The slices of a large split are a fixed
number of voxels per step, so they too are a function of the model, the
samples and the commands only.
"""
from __future__ import annotations

from bonesim.engine.haptics import P_K_LOW, P_RADIUS
from bonesim.engine.model import Model, Sample, State, step
from bonesim.engine.cut_plane import advance_cuts
from bonesim.engine.split_jobs import advance_splits

__all__ = ["world_step", "apply_commands"]


def apply_commands(model: Model, state: State, commands, t_s: float,
                   on_error=None) -> int:
    """Apply world commands to ``state`` in order, at time ``t_s`` [s].

    Parameters
    ----------
    model : Model
    state : State
        Modified in place.
    commands : sequence of WorldCommand
        Anything with ``apply(model, state, t_s)``.
    t_s : float
        Time of the step they precede [s] (their events' time).
    on_error : callable, optional
        ``on_error(i, exc)`` for command ``i`` that raised; the rest are
        still applied. None: the exception propagates (the commands before
        it stay applied).

    Returns
    -------
    int
        Commands applied without error.
    """
    n = 0
    for i, cmd in enumerate(commands):
        if on_error is None:
            cmd.apply(model, state, t_s)
        else:
            try:
                cmd.apply(model, state, t_s)
            except Exception as exc:       # a bad command must not stop the run
                on_error(i, exc)
                continue
        n += 1
    return n


def world_step(model: Model, state: State, sample: Sample, commands=(),
               on_error=None):
    """Advance the world by one haptic sample.

    Parameters
    ----------
    model : Model
        The model; its burr table holds every burr the run may switch to.
    state : State
        Everything the run changes (modified in place).
    sample : Sample
        Time [s], tool centre (case frame) [mm], axis, drill, speed [rpm],
        direction. Its ``burr`` field is not read: the step uses
        ``state.burr``, which only :class:`~bonesim.engine.world_commands.SetBurr`
        changes.
    commands : sequence of WorldCommand
        Applied first, in order, at ``sample.t_s`` (pass an empty tuple when
        there are none: the step then allocates nothing).
    on_error : callable, optional
        ``on_error(i, exc)`` for a command that raised (the others are still
        applied); None: the exception propagates and the sample is not stepped.

    Returns
    -------
    force_n : (3,) float64
        Force to render on the device [N] (a view of ``state.force_n``).

    Raises
    ------
    ValueError
        A sample earlier than the previous step, a non-finite position or a
        zero axis (:func:`~bonesim.engine.model.step`).
    """
    t = float(sample.t_s)
    if commands:
        apply_commands(model, state, commands, t, on_error)
    if state.split_jobs:                   # a large split: one bounded slice per step
        advance_splits(state, t)
    if state.cut_jobs:                     # a large cut-plane stroke: likewise
        advance_cuts(state, t)
    rs = state.rigid
    if rs is not None:                     # poses published before the step
        p = model.burr_params[state.burr]
        rs.advance(state, t, sample.pos_mm, bool(sample.drill), p[P_RADIUS], p[P_K_LOW])
    return step(model, state, sample, state.burr)
