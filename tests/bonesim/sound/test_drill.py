"""Drill sound: spectra of rendered seconds, ramps, output fallback, WAV."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import time
import types
import wave
from pathlib import Path

import numpy as np
import pytest

from bonesim.io.burrs import load_burr
from bonesim.sound.drill import (DECAY_S, NYQUIST_FRACTION, OUTPUT_GAIN, SilentSink, SoundSynth,
                                   WavRecorder, fundamental_hz, open_output, render_seconds)

FS = 48000
CUTTING = load_burr("cutting-5mm")
DIAMOND = load_burr("diamond-3mm")
BURRS = pytest.mark.parametrize("burr", [CUTTING, DIAMOND], ids=["cutting", "diamond"])


def steady(burr, drill=True, speed=None, force=0.0, thickness=math.inf, seconds=1.0,
           seed=0, settle=0.1):
    """``seconds`` of sound after ``settle`` seconds at fixed parameters."""
    s = SoundSynth(burr, FS, seed)
    s.set_params(drill, burr.default_speed_rpm if speed is None else speed, force,
                 thickness)
    render_seconds(s, settle)
    return render_seconds(s, seconds)


def spectrum(x):
    m = np.abs(np.fft.rfft(x.astype(np.float64) * np.hanning(len(x))))
    return np.fft.rfftfreq(len(x), 1.0 / FS), m


def peak_hz(x):
    """Frequency of the strongest line, refined by parabolic interpolation [Hz]."""
    f, m = spectrum(x)
    i = int(np.argmax(m))
    a, b, c = np.log(m[i - 1:i + 2])
    return f[i] + 0.5 * (a - c) / (a - 2 * b + c) * (f[1] - f[0])


def noise_share(x, f0, partials, halfwidth=60.0):
    """Fraction of the energy away from the partials."""
    f, m = spectrum(x)
    e = m ** 2
    mask = np.zeros_like(e, bool)
    for mult, _ in partials:
        mask |= np.abs(f - mult * f0) <= halfwidth
    return e[~mask].sum() / e.sum()


@BURRS
def test_free_running_and_contact_peaks(burr):
    free = peak_hz(steady(burr, force=0.0))
    firm = peak_hz(steady(burr, force=2.0))
    assert free == pytest.approx(burr.sound_base_hz, abs=1.0)
    assert firm == pytest.approx(burr.sound_base_hz + 2.0 * burr.sound_force_hz_per_n,
                                 abs=1.0)
    # the recorded contact peaks (875 Hz cutting, 625 Hz diamond) at 2 N
    assert firm == pytest.approx(burr.vib_contact_hz, abs=1.0)


def test_cutting_and_diamond_differ():
    for force in (0.0, 0.5, 2.0):
        a, b = peak_hz(steady(CUTTING, force=force)), peak_hz(steady(DIAMOND, force=force))
        assert abs(a - b) > 15.0
    # diamond: weaker harmonics, more noise
    f0 = fundamental_hz(CUTTING, CUTTING.default_speed_rpm, 2.0)
    d0 = fundamental_hz(DIAMOND, DIAMOND.default_speed_rpm, 2.0)
    assert (noise_share(steady(DIAMOND, force=2.0), d0, DIAMOND.sound_harmonics)
            > noise_share(steady(CUTTING, force=2.0), f0, CUTTING.sound_harmonics))


@BURRS
def test_pitch_follows_force_as_the_data_says(burr):
    forces = [0.0, 0.5, 1.0, 2.0, 3.0]
    peaks = [peak_hz(steady(burr, force=f)) for f in forces]
    assert np.all(np.diff(peaks) < 0)          # negative Hz/N: the motor slows
    slope = np.polyfit(forces, peaks, 1)[0]
    assert slope == pytest.approx(burr.sound_force_hz_per_n, rel=0.02)


@BURRS
def test_contact_levels_add_noise_and_loudness(burr):
    forces = {"none": 0.0, "light": 0.5, "firm": 2.0}
    shares, rms = {}, {}
    for level, force in forces.items():
        assert burr.contact_level(force) == level
        x = steady(burr, force=force)
        f0 = fundamental_hz(burr, burr.default_speed_rpm, force)
        shares[level] = noise_share(x, f0, burr.sound_harmonics)
        rms[level] = float(np.sqrt(np.mean(x.astype(float) ** 2)))
    assert shares["none"] < shares["light"] < shares["firm"]
    assert rms["none"] < rms["light"] < rms["firm"]
    # partials are still lines in firm contact: the fundamental dominates
    x = steady(burr, force=2.0)
    assert peak_hz(x) == pytest.approx(fundamental_hz(burr, burr.default_speed_rpm, 2.0),
                                       abs=1.0)


@BURRS
def test_pitch_rises_over_thin_bone(burr):
    base = peak_hz(steady(burr, force=1.0, thickness=math.inf))
    thick = peak_hz(steady(burr, force=1.0, thickness=burr.thin_bone_mm + 1.0))
    assert thick == pytest.approx(base, abs=0.5)
    got = []
    for frac in (1.0, 0.75, 0.5, 0.25, 0.0):
        t = frac * burr.thin_bone_mm
        p = peak_hz(steady(burr, force=1.0, thickness=t))
        expect = base * (1.0 + burr.thin_bone_gain * (1.0 - frac))
        assert p == pytest.approx(expect, abs=1.5)
        got.append(p)
    assert np.all(np.diff(got) > 0)
    # NaN thickness means "unknown": no rise
    assert peak_hz(steady(burr, force=1.0, thickness=math.nan)) == pytest.approx(base, abs=0.5)


@BURRS
def test_pitch_scales_with_speed(burr):
    base = peak_hz(steady(burr))
    fast = peak_hz(steady(burr, speed=burr.max_speed_rpm))
    assert fast == pytest.approx(base * burr.max_speed_rpm / burr.default_speed_rpm, abs=1.5)
    slow = peak_hz(steady(burr, speed=0.5 * burr.default_speed_rpm))
    assert slow == pytest.approx(0.5 * base, abs=1.0)


def test_no_partials_above_nyquist():
    # a burr whose 8th partial lands above the limit at 16 kHz sampling
    fs = 16000
    s = SoundSynth(CUTTING, fs)
    s.set_params(True, CUTTING.max_speed_rpm, 0.0)
    render_seconds(s, 0.1)
    x = render_seconds(s, 1.0)
    f0 = fundamental_hz(CUTTING, CUTTING.max_speed_rpm, 0.0)
    assert 8 * f0 > NYQUIST_FRACTION * fs / 2 > 4 * f0
    m = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    f = np.fft.rfftfreq(len(x), 1.0 / fs)
    alias = fs - 8 * f0                                   # where the 8th would fold
    near = np.abs(f - alias) < 20
    ref = np.abs(f - f0) < 20
    assert m[near].max() < 0.02 * m[ref].max()


@BURRS
def test_silent_with_drill_off_or_stopped(burr):
    assert not steady(burr, drill=False, force=2.0).any()
    assert not steady(burr, speed=0.0, force=2.0).any()


def test_stopping_decays_without_a_click():
    # a pure tone so that any discontinuity shows up as a jump between samples
    burr = dataclasses.replace(CUTTING, sound_noise=0.0, sound_harmonics=((1.0, 1.0),))
    s = SoundSynth(burr, FS)
    s.set_params(True, burr.default_speed_rpm, 0.0)
    on = render_seconds(s, 0.2)
    s.set_params(False, burr.default_speed_rpm, 0.0)
    off = render_seconds(s, 0.1)
    x = np.concatenate([on, off]).astype(float)
    # still sounding early in the decay, exactly silent once it is over
    n_decay = int(DECAY_S * FS) + 256
    assert np.abs(off[:n_decay // 2]).max() > 0
    assert not off[n_decay:].any()
    # sample-to-sample steps never exceed a sine's own slope (no click)
    amp = np.abs(on[FS // 20:]).max()
    slope = amp * 2 * np.pi * burr.sound_base_hz / FS
    assert np.abs(np.diff(x)).max() <= 1.6 * slope
    # the envelope decays monotonically (peaks of 32-sample chunks)
    chunks = np.abs(off[:n_decay].reshape(-1, 32)).max(axis=1)
    env = np.maximum.accumulate(chunks[::-1])[::-1]
    assert np.all(np.diff(env) <= 1e-9)
    # and starting again ramps up from silence
    s.set_params(True, burr.default_speed_rpm, 0.0)
    again = render_seconds(s, 0.05)
    assert abs(again[0]) < 0.05 * amp and np.abs(np.diff(again)).max() <= 1.6 * slope


def test_parameter_jumps_glide():
    burr = dataclasses.replace(CUTTING, sound_noise=0.0, sound_harmonics=((1.0, 1.0),))
    s = SoundSynth(burr, FS)
    s.set_params(True, burr.default_speed_rpm, 0.0)
    a = render_seconds(s, 0.1)
    s.set_params(True, burr.default_speed_rpm, 3.0, 0.0)          # firm, thin: big jump
    b = render_seconds(s, 0.1)
    x = np.concatenate([a, b]).astype(float)
    amp = np.abs(x).max()
    fmax = fundamental_hz(burr, burr.default_speed_rpm, 0.0, 0.0) * 1.0
    fmax = max(fmax, fundamental_hz(burr, burr.default_speed_rpm, 3.0, 0.0))
    assert np.abs(np.diff(x)).max() <= 1.1 * amp * 2 * np.pi * fmax / FS


def test_deterministic_with_a_seed():
    def run(seed):
        s = SoundSynth(DIAMOND, FS, seed)
        out = []
        for q, f in enumerate(np.linspace(0, 3, 40)):
            s.set_params(q % 13 != 12, 40000.0 + 500 * q, f, 3.0 - f)
            out.append(render_seconds(s, 256 / FS))
        return np.concatenate(out)

    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    s = SoundSynth(DIAMOND, FS, 5)
    s.set_params(True, 40000.0, 1.0)
    first = render_seconds(s, 0.05)
    s.reset()
    assert np.array_equal(render_seconds(s, 0.05), first)


def test_block_size_does_not_matter_much_and_render_checks():
    s = SoundSynth(CUTTING, FS)
    s.set_params(True, CUTTING.default_speed_rpm, 1.5)
    x = render_seconds(s, 0.5, block=100)
    assert peak_hz(x[4800:]) == pytest.approx(
        fundamental_hz(CUTTING, CUTTING.default_speed_rpm, 1.5), abs=2.0)
    assert np.abs(x).max() <= 1.0
    with pytest.raises(ValueError):
        s.render(np.zeros(16))                      # float64
    with pytest.raises(ValueError):
        s.render(np.zeros((16, 2), np.float32))
    # the callback's column view (strided) renders too
    buf = np.zeros((64, 2), np.float32)
    s.render(buf[:, 0])
    assert buf[:, 0].any() and not buf[:, 1].any()


def test_set_burr_switches_the_sound():
    s = SoundSynth(CUTTING, FS)
    s.set_params(True, 40000.0, 2.0)
    render_seconds(s, 0.1)
    assert peak_hz(render_seconds(s, 1.0)) == pytest.approx(
        fundamental_hz(CUTTING, 40000.0, 2.0), abs=1.0)
    s.set_burr(DIAMOND)
    render_seconds(s, 0.1)
    assert peak_hz(render_seconds(s, 1.0)) == pytest.approx(
        fundamental_hz(DIAMOND, 40000.0, 2.0), abs=1.0)


# ------------------------------------------------------------------ output
def _hide_sounddevice(monkeypatch):
    monkeypatch.setitem(sys.modules, "sounddevice", None)     # import -> ImportError


def test_fallback_when_sounddevice_cannot_be_imported(monkeypatch, capsys):
    _hide_sounddevice(monkeypatch)
    s = SoundSynth(CUTTING, FS)
    s.set_params(True, 60000.0, 1.0)
    out = open_output(s)
    try:
        assert isinstance(out, SilentSink)
        assert out.notice and "no audio output" in out.notice
        time.sleep(0.05)
    finally:
        out.close()
    out.close()                                            # idempotent
    err = capsys.readouterr().err
    assert err.count("no audio output") == 1 and out.notice in err
    assert s.envelope > 0                                  # it rendered in real time


def _fake_sounddevice(fail_with=None):
    mod = types.ModuleType("sounddevice")

    class PortAudioError(Exception):
        pass

    class OutputStream:
        def __init__(self, samplerate, blocksize, channels, dtype, callback, device):
            if fail_with == "portaudio":
                raise PortAudioError("Error querying device -1")
            if fail_with == "device":
                raise ValueError(f"No output device matching {device!r}")
            self.callback, self.blocksize, self.started = callback, blocksize, False

        def start(self):
            self.started = True

        def stop(self):
            self.started = False

        def close(self):
            pass

    mod.PortAudioError = PortAudioError
    mod.OutputStream = OutputStream
    return mod


@pytest.mark.parametrize("failure", ["portaudio", "device"])
def test_fallback_on_portaudio_or_device_errors(monkeypatch, capsys, failure):
    monkeypatch.setitem(sys.modules, "sounddevice", _fake_sounddevice(failure))
    out = open_output(SoundSynth(CUTTING, FS), device="nope", realtime_fallback=False)
    out.close()
    assert isinstance(out, SilentSink)
    assert capsys.readouterr().err.count("no audio output") == 1


def test_stream_callback_renders_and_records(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "sounddevice", _fake_sounddevice())
    s = SoundSynth(DIAMOND, FS)
    s.set_params(True, 40000.0, 1.0)
    rec = WavRecorder(tmp_path / "cb.wav", FS)
    out = open_output(s, recorder=rec)
    assert out.notice is None and out.stream.started
    buf = np.zeros((256, 1), np.float32)
    for _ in range(4):
        out.stream.callback(buf, 256, None, None)
    assert buf.any()
    out.close()
    rec.close()
    assert rec.frames == 1024 and capsys.readouterr().err == ""


def test_real_environment_never_crashes(capsys):
    # here there is no PortAudio library / sound card: expect the notice
    s = SoundSynth(CUTTING, FS)
    out = open_output(s, realtime_fallback=False)
    out.close()
    if isinstance(out, SilentSink):
        assert capsys.readouterr().err.count("no audio output") == 1


def test_wav_recorder(tmp_path):
    s = SoundSynth(CUTTING, FS)
    s.set_params(True, 60000.0, 2.0, 1.0)
    path = tmp_path / "drill.wav"
    blocks = []
    with WavRecorder(path, FS) as rec:
        buf = np.zeros(256, np.float32)
        for _ in range(50):
            s.render(buf)
            rec.write(buf)
            blocks.append(buf.copy())
        rec.write(np.array([2.0, -2.0], np.float32))      # clipped
    with wave.open(str(path), "rb") as w:
        assert (w.getnchannels(), w.getsampwidth(), w.getframerate()) == (1, 2, FS)
        assert w.getnframes() == 50 * 256 + 2
        pcm = np.frombuffer(w.readframes(w.getnframes()), dtype="<i2")
    x = np.concatenate(blocks)
    assert np.abs(pcm[:-2] / 32767.0 - x).max() <= 0.5 / 32767 + 1e-7
    assert list(pcm[-2:]) == [32767, -32767]
    assert peak_hz(pcm[FS // 10:].astype(float)) == pytest.approx(
        fundamental_hz(CUTTING, 60000.0, 2.0, 1.0), abs=2.0)


def test_silent_sink_records_at_real_time_pace(tmp_path):
    s = SoundSynth(CUTTING, FS)
    s.set_params(True, 60000.0, 0.5)
    rec = WavRecorder(tmp_path / "silent.wav", FS)
    sink = SilentSink(s, 256, rec)
    t0 = time.perf_counter()
    time.sleep(0.2)
    sink.close()
    elapsed = time.perf_counter() - t0
    rec.close()
    assert 0 < rec.frames <= (elapsed + 0.05) * FS + 256


def test_importing_does_not_load_sounddevice():
    code = ("import sys, bonesim, bonesim.sound.drill, bonesim.physics.vibration, bonesim.engine.thickness, "
            "bonesim.bench.sound; print('sounddevice' in sys.modules)")
    repo = Path(__file__).resolve().parents[3]
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=repo)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "False"


def test_output_level_is_bounded():
    for burr in (CUTTING, DIAMOND):
        x = steady(burr, force=3.3, thickness=0.0, speed=burr.max_speed_rpm)
        assert np.abs(x).max() < 1.0 and np.abs(x).max() > 0.3 * OUTPUT_GAIN
