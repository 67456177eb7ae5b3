"""The drill's sound, in its own process, steered by the haptic loop.

Audio callbacks need the interpreter lock every few milliseconds; in the
window's process VTK holds it for whole frames, and the haptic process must
not be disturbed. So the synthesizer (:mod:`bonesim.sound.drill`) runs in a small
process of its own. It reads the haptic loop's shared status (drill, speed,
applied force, tool position, burr) at :data:`CONTROL_HZ`, estimates the bone
thickness under the burr by ray casting (:mod:`bonesim.engine.thickness`) on the
shared tissue (density and the body arrays: each body near the burr is read in
its own frame, at the pose the loop holds now), and hands the four numbers to
the synthesizer, whose output stream (or silent sink, without a sound
device) renders blocks in its own callback. ``wav`` records exactly what is rendered.

With a nerve monitor (:class:`bonesim.runtime.monitor.MonitorProcess`) the same
process also drains the monitor's spikes and mixes a click per spike into the
same stream (:mod:`bonesim.sound.clicks`), ``clicks.DELAY_S`` after the spike.
"""
from __future__ import annotations

import time

import numpy as np

from bonesim.runtime.child import ChildProcess
from bonesim.runtime.shared import SharedArrays

__all__ = ["CONTROL_HZ", "THICKNESS_MAX_MM", "AudioProcess"]

#: Rate at which sound parameters follow the haptic loop [Hz].
CONTROL_HZ = 100.0
#: Longest ray cast for the thickness estimate [mm].
THICKNESS_MAX_MM = 6.0


def _run_audio(child, loop_handle, model, burrs, wav, monitor=None) -> None:
    """Body of the audio process (:meth:`AudioProcess.run`)."""
    from bonesim.engine.bodies import Bodies
    from bonesim.engine.grid import Grid
    from bonesim.sound.drill import SoundSynth, WavRecorder, open_output
    from bonesim.sound.drill import warmup as sound_warmup
    from bonesim.engine.thickness import bone_thickness_mm
    from bonesim.engine.thickness import warmup as thickness_warmup

    sh = SharedArrays.attach(loop_handle)
    astat = child.status
    status = sh["status"]
    g0 = model.grid
    grid = Grid(g0.spacing_mm, g0.origin_mm, g0.shape, g0.keys, g0.vals, g0.bricks,
                sh["density"], g0.label)
    bodies = Bodies.of(sh.arrays)          # body, pose, pose_m, alive, bounds
    all_burrs = [model.burr] + [b for b in burrs if b is not None]
    sound_warmup()
    thickness_warmup()
    synth = SoundSynth(all_burrs[0])
    recorder = WavRecorder(wav, synth.sample_rate) if wav else None
    clicks = None
    if monitor is not None:                 # (handle, nerves): clicks for its spikes
        from bonesim.sound.clicks import ClickSynth, MixedSynth
        from bonesim.sound.clicks import warmup as clicks_warmup
        from bonesim.runtime.monitor import shared_rings

        clicks_warmup()
        msh = SharedArrays.attach(monitor[0])
        spikes = shared_rings(msh.arrays)[1]
        spike_pos = spikes.count
        clicks = ClickSynth(synth.sample_rate, monitor[1])
        clicks.sync(float(status["t_s"]))       # provisional: re-anchored once it renders
    out = open_output(synth if clicks is None else MixedSynth(synth, clicks),
                      recorder=recorder, say=False)   # the simulator notes it once
    astat["silent"] = 0 if out.notice is None else 1
    child.ready()
    burr = 0
    try:
        while not child.quit:
            b = int(status["burr"])
            if b != burr and 0 <= b < len(all_burrs):
                burr = b
                synth.set_burr(all_burrs[b])
            drill = bool(status["drill"])
            force = float(status["mag_n"])
            thick = float("inf")
            if drill and force > 0.0:
                thick = bone_thickness_mm(grid, status["pos_mm"].copy(),
                                          all_burrs[burr].radius_mm, THICKNESS_MAX_MM,
                                          bodies=bodies)
            synth.set_params(drill, float(status["speed_rpm"]), force, thick)
            if clicks is not None:
                astat["anchors"] += clicks.sync(float(status["t_s"]))
                head = spikes.count
                if head > spike_pos:
                    rec = spikes.read(max(spike_pos, head - spikes.capacity // 2), head)
                    clicks.schedule(rec["t_s"], rec["nerve"])
                    spike_pos = head
                astat["clicks"] = clicks.scheduled
                astat["late"] = clicks.late
                astat["dropped"] = clicks.dropped
            time.sleep(1.0 / CONTROL_HZ)
    finally:
        out.close()
        if recorder is not None:
            recorder.close()
        sh.close()


class AudioProcess(ChildProcess):
    """Plays (or records) the drill sound of a running :class:`HapticLoop`.

    Parameters
    ----------
    loop : HapticLoop
        The loop whose status steers the sound.
    wav : path, optional
        Also write everything rendered to this WAV file.
    monitor : MonitorProcess, optional
        Mix a click per spike of this nerve monitor into the sound.

    Attributes
    ----------
    status : ndarray
        ``silent`` (no sound device) and, with a monitor, the ``clicks``
        scheduled, sounded ``late``, ``dropped`` (ring full) and clock
        re-``anchors``.
    """

    NAME = "bonesim-audio"
    STATUS = (("silent", np.uint8), ("clicks", np.int64), ("late", np.int64),
              ("dropped", np.int64), ("anchors", np.int64))
    START_REQUIRED = False          # a slow start is not fatal: silent until ready

    def __init__(self, loop, wav=None, monitor=None):
        self.loop = loop
        self.wav = None if wav is None else str(wav)
        self.monitor = None if monitor is None else (monitor.handle, len(monitor.names))
        super().__init__()

    def child_args(self) -> dict:
        return {"loop_handle": self.loop.handle, "model": self.loop.model,
                "burrs": self.loop.burrs[1:], "wav": self.wav, "monitor": self.monitor}

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_audio(child, **kwargs)

    @property
    def silent(self) -> bool:
        """True when no sound device was found (a silent sink renders instead)."""
        return bool(self.status["silent"])

    def click_stats(self) -> dict:
        """The nerve monitor's clicks so far: scheduled, sounded late (their
        spike came after the click delay), dropped (ring full) and clock
        re-anchors (the first one included)."""
        s = self.status
        return {"clicks": int(s["clicks"]), "late": int(s["late"]),
                "dropped": int(s["dropped"]), "anchors": int(s["anchors"])}
