"""The drill's sound, in its own process, steered by the haptic loop.

Audio callbacks need the interpreter lock every few milliseconds; in the
window's process VTK holds it for whole frames, and the haptic process must
not be disturbed. So the synthesizer (:mod:`bonesim.sound`) runs in a small
process of its own. It reads the haptic loop's shared status (drill, speed,
applied force, tool position, burr) at :data:`CONTROL_HZ`, estimates the bone
thickness under the burr by ray casting (:mod:`bonesim.thickness`) on the
shared tissue, and hands the four numbers to the synthesizer, whose output
stream (or silent sink, without a sound device) renders blocks in its own
callback. ``wav`` records exactly what is rendered.

With a nerve monitor (:class:`bonesim.monitor.MonitorProcess`) the same
process also drains the monitor's spikes and mixes a click per spike into the
same stream (:mod:`bonesim.clicks`), ``clicks.DELAY_S`` after the spike.
"""
from __future__ import annotations

import time

from .shared import SharedArrays, die_with_parent, end_process, start_process, wait_ready

__all__ = ["CONTROL_HZ", "THICKNESS_MAX_MM", "A_READY", "A_SILENT", "A_DONE", "A_QUIT",
           "A_CLICKS", "A_LATE", "A_DROPPED", "A_ANCHORS", "N_AS", "AudioProcess"]

#: Rate at which sound parameters follow the haptic loop [Hz].
CONTROL_HZ = 100.0
#: Longest ray cast for the thickness estimate [mm].
THICKNESS_MAX_MM = 6.0
# audio status slots (written by the audio process): ready, no device, done,
# quit; with a monitor the clicks scheduled, sounded late, dropped (ring full)
# and clock re-anchors
A_READY, A_SILENT, A_DONE, A_QUIT, A_CLICKS, A_LATE, A_DROPPED, A_ANCHORS = range(8)
N_AS = 8


def _audio_main(handle, model, burrs, wav, status_handle, monitor=None) -> None:
    from .grid import Grid
    from .haptic_loop import ST_BURR, ST_DRILL, ST_MAG, ST_POS, ST_SPEED, ST_T
    from .sound import SoundSynth, WavRecorder, open_output
    from .sound import warmup as sound_warmup
    from .thickness import bone_thickness_mm
    from .thickness import warmup as thickness_warmup

    die_with_parent()
    sh = SharedArrays.attach(handle)
    ash = SharedArrays.attach(status_handle)
    astat = ash["audio"]
    status = sh["status"]
    g0 = model.grid
    grid = Grid(g0.spacing_mm, g0.origin_mm, g0.shape, g0.keys, g0.vals, g0.bricks,
                sh["density"], g0.label)
    all_burrs = [model.burr] + [b for b in burrs if b is not None]
    sound_warmup()
    thickness_warmup()
    synth = SoundSynth(all_burrs[0])
    recorder = WavRecorder(wav, synth.sample_rate) if wav else None
    clicks = None
    if monitor is not None:                 # (handle, nerves): clicks for its spikes
        from .clicks import ClickSynth, MixedSynth
        from .clicks import warmup as clicks_warmup
        from .monitor import shared_rings

        clicks_warmup()
        msh = SharedArrays.attach(monitor[0])
        spikes = shared_rings(msh.arrays)[1]
        spike_pos = spikes.count
        clicks = ClickSynth(synth.sample_rate, monitor[1])
        clicks.sync(float(status[ST_T]))        # provisional: re-anchored once it renders
    out = open_output(synth if clicks is None else MixedSynth(synth, clicks),
                      recorder=recorder)
    astat[A_SILENT] = 0.0 if out.notice is None else 1.0
    astat[A_READY] = 1.0
    burr = 0
    try:
        while astat[A_QUIT] == 0.0:
            b = int(status[ST_BURR])
            if b != burr and 0 <= b < len(all_burrs):
                burr = b
                synth.set_burr(all_burrs[b])
            drill = bool(status[ST_DRILL])
            force = float(status[ST_MAG])
            thick = float("inf")
            if drill and force > 0.0:
                thick = bone_thickness_mm(grid, status[ST_POS:ST_POS + 3].copy(),
                                          all_burrs[burr].radius_mm, THICKNESS_MAX_MM)
            synth.set_params(drill, float(status[ST_SPEED]), force, thick)
            if clicks is not None:
                astat[A_ANCHORS] += clicks.sync(float(status[ST_T]))
                head = spikes.count
                if head > spike_pos:
                    rec = spikes.read(max(spike_pos, head - spikes.capacity // 2), head)
                    clicks.schedule(rec["t_s"], rec["nerve"])
                    spike_pos = head
                astat[A_CLICKS] = clicks.scheduled
                astat[A_LATE] = clicks.late
                astat[A_DROPPED] = clicks.dropped
            time.sleep(1.0 / CONTROL_HZ)
    finally:
        out.close()
        if recorder is not None:
            recorder.close()
        astat[A_DONE] = 1.0
        ash.close()
        sh.close()


class AudioProcess:
    """Plays (or records) the drill sound of a running :class:`HapticLoop`.

    Parameters
    ----------
    loop : HapticLoop
        The loop whose status steers the sound.
    wav : path, optional
        Also write everything rendered to this WAV file.
    monitor : MonitorProcess, optional
        Mix a click per spike of this nerve monitor into the sound.
    """

    def __init__(self, loop, wav=None, monitor=None):
        import numpy as np

        self.loop = loop
        self.wav = None if wav is None else str(wav)
        self.monitor = None if monitor is None else (monitor.handle, len(monitor.names))
        self._ash = SharedArrays.create([("audio", (N_AS,), np.float64)])
        self.status = self._ash["audio"]
        self._proc = None

    def start(self, timeout_s: float = 60.0) -> "AudioProcess":
        self._proc = start_process(
            _audio_main, "bonesim-audio",
            (self.loop.handle, self.loop.model, self.loop.burrs[1:], self.wav,
             self._ash.handle, self.monitor))
        # a slow start is not fatal: the drill is silent until it is ready
        if wait_ready(self._proc, lambda: self.status[A_READY] != 0.0, timeout_s) == "exited":
            raise RuntimeError("the audio process exited during start-up "
                               f"(exit code {self._proc.exitcode})")
        return self

    @property
    def silent(self) -> bool:
        """True when no sound device was found (a silent sink renders instead)."""
        return bool(self.status[A_SILENT])

    def click_stats(self) -> dict:
        """The nerve monitor's clicks so far: scheduled, sounded late (their
        spike came after the click delay), dropped (ring full) and clock
        re-anchors (the first one included)."""
        s = self.status
        return {"clicks": int(s[A_CLICKS]), "late": int(s[A_LATE]),
                "dropped": int(s[A_DROPPED]), "anchors": int(s[A_ANCHORS])}

    def close(self, timeout_s: float = 5.0) -> None:
        if self._ash is None:
            return
        self.status[A_QUIT] = 1.0
        if self._proc is not None:
            end_process(self._proc, timeout_s)
            self._proc = None
        self._ash.close()
        self._ash = None
