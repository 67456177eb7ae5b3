"""Haptic tutoring and haptic playback: the control law, the instructor's server,
the trainee's sources and servo (and its process).

The trainee's device is driven by a low-gain position controller toward the
instructor's tool plus the instructor's own force (see ``SPEC.md``,
"Training features beyond a cadaver lab")::

    F_trainee = K_p (P_instructor - P_trainee) + F_instructor

clamped to the trainee device's force limit (:func:`~bonesim.tutoring.law.tutor_force`). The
instructor's force carries the bone's contact force, the burr's drag and its
vibration; the weak spring keeps the trainee's tool near the instructor's
without masking them. Where the instructor's state comes from is a
:class:`~bonesim.tutoring.sources.Source`:

:class:`~bonesim.tutoring.sources.NetworkSource`
    live, from an instructor's :class:`~bonesim.tutoring.server.TutorServer` over authenticated UDP
    (:mod:`bonesim.net.packets`): ``bonesim tutor serve`` / ``bonesim tutor join``.
:class:`~bonesim.tutoring.sources.RecordingSource`
    a recorded session file (haptic playback): ``bonesim tutor playback``.

A :class:`~bonesim.tutoring.servo.Trainee` runs the servo tick at 1 kHz: poll the source, read the
device, compute the force, write it. When the source goes quiet (network
loss, end of a recording) the force ramps to zero within
:data:`~bonesim.net.tutor_protocol.LOSS_S` + :data:`~bonesim.net.tutor_protocol.RAMP_S` = 45 ms of the last valid data, and
:attr:`~bonesim.tutoring.servo.Trainee.link_lost` / the HUD text say so; when data returns the force
fades back in over :data:`~bonesim.net.tutor_protocol.RECOVER_S`.

The pieces live in their own modules, and each name is imported from the
module that defines it:
:mod:`bonesim.net.tutor_protocol` (constants, the state on the wire, the
tissue-event log and the late joiner's snapshot), :mod:`bonesim.tutoring.law` (the force and the link gain),
:mod:`bonesim.tutoring.server` (streamer and server), :mod:`bonesim.tutoring.sources`
(network and recording sources), :mod:`bonesim.tutoring.servo` (the servo) and
:mod:`bonesim.cli.tutor` (``bonesim tutor ...``).

The wire protocol (join, welcome, acknowledgements, STATE packets carrying
tissue-event records, and the go-back-N event log) is described in
:mod:`bonesim.net.tutor_protocol`. The trainee's tissue is one
:class:`~bonesim.engine.replica.TissueReplica` fed by that stream.
"""

__all__: list[str] = []
