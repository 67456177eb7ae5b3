"""Haptic tutoring and haptic playback.

The trainee's device is driven by a low-gain position controller toward the
instructor's tool plus the instructor's own force (see ``SPEC.md``,
"Training features beyond a cadaver lab")::

    F_trainee = K_p (P_instructor - P_trainee) + F_instructor

clamped to the trainee device's force limit (:func:`tutor_force`). The
instructor's force carries the bone's contact force, the burr's drag and its
vibration; the weak spring keeps the trainee's tool near the instructor's
without masking them. Where the instructor's state comes from is a
:class:`Source`:

:class:`NetworkSource`
    live, from an instructor's :class:`TutorServer` over authenticated UDP
    (:mod:`bonesim.net.packets`): ``bonesim tutor serve`` / ``bonesim tutor join``.
:class:`RecordingSource`
    a recorded session file (haptic playback): ``bonesim tutor playback``.

A :class:`Trainee` runs the servo tick at 1 kHz: poll the source, read the
device, compute the force, write it. When the source goes quiet (network
loss, end of a recording) the force ramps to zero within
:data:`LOSS_S` + :data:`RAMP_S` = 45 ms of the last valid data, and
:attr:`Trainee.link_lost` / the HUD text say so; when data returns the force
fades back in over :data:`RECOVER_S`.

The pieces live in their own modules and are gathered here:
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
from __future__ import annotations

from bonesim.net.packets import udp_socket  # noqa: F401 (tests and tools reach it here)
from bonesim.net.tutor_protocol import (ACK, CLIENT_TIMEOUT_S, DEFAULT_PORT, FLAG_NACK,
                                        JOIN_RETRY_S, KEEPALIVE_S, KIND_STATE, KP_N_PER_MM,
                                        LOSS_S, MAX_BURST, MAX_EVENTS, NACK_HOLD_S, RAMP_S, RECORD,
                                        RECOVER_S, REJOIN_S, SERVO_HZ, STALE_S, STATE,
                                        InstructorState, TissueLog, check_tissue_version,
                                        pack_state, session_info, tissue_snapshot, unpack_state)
from bonesim.tutoring.law import link_gain, tutor_force
from bonesim.tutoring.server import Streamer, TutorServer
from bonesim.tutoring.sources import NetworkSource, RecordingSource, Source
from bonesim.tutoring.servo import Trainee, warmup

__all__ = ["ACK", "CLIENT_TIMEOUT_S", "DEFAULT_PORT", "FLAG_NACK", "JOIN_RETRY_S",
           "KEEPALIVE_S", "KIND_STATE", "KP_N_PER_MM", "LOSS_S", "MAX_BURST", "MAX_EVENTS",
           "NACK_HOLD_S", "RAMP_S", "RECORD", "RECOVER_S", "REJOIN_S", "SERVO_HZ",
           "STALE_S", "STATE", "InstructorState", "TissueLog", "check_tissue_version",
           "pack_state", "session_info", "tissue_snapshot", "unpack_state", "link_gain",
           "tutor_force", "Streamer", "TutorServer", "NetworkSource",
           "RecordingSource", "Source", "Trainee", "warmup"]
