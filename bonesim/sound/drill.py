"""Data-driven drill sound: noisy harmonics steered by the haptic loop.

The sound of a burr is synthesized from its file's data (see
:class:`bonesim.io.burrs.Burr`): partials at multiples of a fundamental, each
slightly noisy, plus a band of cutting noise. The haptic loop hands the
synthesizer four numbers (:meth:`SoundSynth.set_params`); the audio side
renders blocks from them (:meth:`SoundSynth.render`), in an audio callback
(:func:`open_output`) or into a WAV file (:class:`WavRecorder`).

Sound law
---------
With ``phi = speed / default_speed`` (clamped to ``[0, max / default]``),
``F`` the applied force clamped to ``[0, max_force_n]`` and ``T`` the bone
thickness under the burr [mm] (see :mod:`bonesim.engine.thickness`; ``inf`` or NaN
when unknown)::

    rise = thin_bone_gain * clip((thin_bone_mm - T) / thin_bone_mm, 0, 1)
    f0   = phi * (sound_base_hz + sound_force_hz_per_n * F) * (1 + rise)   [Hz]

so the pitch follows the motor speed, drops under load as the data says
(-77.5 Hz/N for the cutting burrs: 1030 Hz free, 875 Hz at 2 N), and rises
linearly as the bone thins below ``thin_bone_mm``, up to ``+thin_bone_gain``
at zero thickness.

The signal is::

    y = OUTPUT_GAIN * env * (tone * sum_k a_k (1 + depth * r_k) sin(2 pi p_k) / sum_k a_k
                             + noise * b)

* partial ``k`` runs at ``m_k * f0`` (``sound_harmonics`` gives ``(m_k,
  a_k)``); its phase ``p_k`` is accumulated so pitch changes never jump the
  waveform; partials at or above ``NYQUIST_FRACTION * sample_rate / 2`` are
  muted;
* ``r_k`` is unit-variance noise low-passed at ``JITTER_HZ``: it modulates the
  partial's amplitude by ``depth``, turning each line into a narrow noisy band
  (the "noisy harmonics");
* ``b`` is white noise through a band-pass centred at ``NOISE_CENTRE * f0``
  (quality ``NOISE_Q``), normalized to about unit RMS: the cutting noise;
* the contact level (``none`` below ``sound_contact_light_n``, ``light``,
  ``firm`` from ``sound_contact_firm_n``; :meth:`Burr.contact_level`) sets
  ``tone = (1 - sound_noise) * LEVEL_TONE[level]``,
  ``noise = sound_noise * LEVEL_NOISE[level]`` and ``depth =
  LEVEL_DEPTH[level]``: free running is a clean whine, contact adds cutting
  noise, louder and rougher partials.

Smoothness: each block (of any length) moves ``f0``, ``tone``, ``noise`` and
``depth`` linearly from their values at the end of the previous block to the
new targets, and the envelope ``env`` toward 1 (drill running) or 0 at
``1 / ATTACK_S`` or ``1 / DECAY_S`` per second, so starting, stopping and
parameter jumps are ramps, never clicks. With the drill off (or at zero
speed) the sound decays in ``DECAY_S`` and then the output is exactly 0.

Determinism: the noise comes from a xorshift64* generator seeded from
``seed``, the partials' start phases from ``numpy.random.default_rng(seed)``;
the same seed and the same parameter sequence give bit-identical samples.

Threads: :meth:`SoundSynth.set_params` only writes four floats into a small
array that :meth:`SoundSynth.render` reads once per block; no lock is taken
(a block may see a half-updated set of parameters, which only matters for one
block). Exactly one thread may render a given synthesizer.

``sounddevice`` (PortAudio) is imported only inside :func:`open_output`.

Use::

    synth = SoundSynth(model.burr)
    rec = WavRecorder(path, synth.sample_rate) if wav else None   # --wav FILE
    out = open_output(synth, recorder=rec)    # never raises; out.notice says why muted
    ...  # haptic loop, every step or every few ms:
    synth.set_params(sample.drill, sample.speed_rpm, state.out[O_MAG],
                     bone_thickness_mm(state.grid, state.pos_mm, model.burr.radius_mm))
    ...
    out.close(); rec and rec.close()
"""
from __future__ import annotations

import math
import sys
import threading
import time
import wave
from pathlib import Path

import numpy as np
from numba import njit

__all__ = ["SAMPLE_RATE", "BLOCK", "OUTPUT_GAIN", "NYQUIST_FRACTION", "ATTACK_S", "DECAY_S",
           "JITTER_HZ", "NOISE_CENTRE", "NOISE_Q", "LEVEL_TONE", "LEVEL_NOISE", "LEVEL_DEPTH",
           "MAX_PARTIALS", "SoundSynth", "SilentSink", "AudioOutput", "WavRecorder",
           "open_output", "render_seconds", "fundamental_hz", "warmup"]

#: Default output sample rate [Hz].
SAMPLE_RATE = 48000
#: Default block length of the audio callback [samples].
BLOCK = 256
#: Peak scale of the mix (keeps the sum of partials and noise below 1).
OUTPUT_GAIN = 0.25
#: Partials are muted at or above this fraction of the Nyquist frequency.
NYQUIST_FRACTION = 0.9
#: Time for the envelope to rise from 0 to 1 when the drill starts [s].
ATTACK_S = 0.01
#: Time for the envelope to fall from 1 to 0 when the drill stops [s].
DECAY_S = 0.03
#: Bandwidth of the amplitude noise of each partial [Hz].
JITTER_HZ = 40.0
#: Centre of the cutting-noise band, as a multiple of the fundamental.
NOISE_CENTRE = 3.0
#: Quality factor of the cutting-noise band-pass (low: a broad band).
NOISE_Q = 0.8
#: Tone gain per contact level (none, light, firm).
LEVEL_TONE = (0.7, 0.85, 1.0)
#: Noise gain per contact level (none, light, firm), times ``sound_noise``.
LEVEL_NOISE = (0.15, 0.6, 1.0)
#: Amplitude-noise depth of the partials per contact level (none, light, firm).
LEVEL_DEPTH = (0.1, 0.3, 0.5)
#: Most partials a burr may list.
MAX_PARTIALS = 16

# set_params() vector
P_DRILL, P_SPEED_RPM, P_FORCE_N, P_THICKNESS_MM = range(4)
N_PARAMS = 4
# burr vector: scalars, then MAX_PARTIALS multiples, then MAX_PARTIALS amplitudes
(B_BASE_HZ, B_HZ_PER_N, B_NOISE, B_LIGHT_N, B_FIRM_N, B_THIN_MM, B_THIN_GAIN,
 B_DEFAULT_RPM, B_MAX_RPM, B_MAX_FORCE_N, B_N_PARTIALS) = range(11)
B_MULT = 11
B_AMP = B_MULT + MAX_PARTIALS
N_BURR = B_AMP + MAX_PARTIALS
# synthesizer state
(S_ENV, S_F0, S_TONE, S_NOISE, S_DEPTH, S_X1, S_X2, S_Y1, S_Y2) = range(9)
N_STATE = 9
_TWO_PI = 2.0 * math.pi
_LEVEL_TONE = np.array(LEVEL_TONE)
_LEVEL_NOISE = np.array(LEVEL_NOISE)
_LEVEL_DEPTH = np.array(LEVEL_DEPTH)


# --------------------------------------------------------------------- law
@njit(cache=True, nogil=True)
def _targets(params, burr):
    """``(running, f0 [Hz], level)`` for the current parameters."""
    default = burr[B_DEFAULT_RPM]
    speed = params[P_SPEED_RPM]
    phi = speed / default if speed > 0.0 else 0.0         # NaN -> 0
    phi = min(phi, burr[B_MAX_RPM] / default)
    running = params[P_DRILL] > 0.5 and phi > 0.0
    force = abs(params[P_FORCE_N])
    if not force >= 0.0:                                  # NaN
        force = 0.0
    force = min(force, burr[B_MAX_FORCE_N])
    thin = burr[B_THIN_MM]
    thick = params[P_THICKNESS_MM]
    rise = 0.0
    if thick < thin:                                      # False for NaN / inf
        rise = burr[B_THIN_GAIN] * min(1.0, (thin - max(thick, 0.0)) / thin)
    f0 = phi * (burr[B_BASE_HZ] + burr[B_HZ_PER_N] * force) * (1.0 + rise)
    if force < burr[B_LIGHT_N]:
        level = 0
    elif force < burr[B_FIRM_N]:
        level = 1
    else:
        level = 2
    return running, max(f0, 0.0), level


def fundamental_hz(burr, speed_rpm: float, force_n: float,
                   thickness_mm: float = math.inf) -> float:
    """The fundamental [Hz] the synthesizer aims for (the sound law above).

    Parameters
    ----------
    burr : Burr
    speed_rpm : float
        Drill speed [rpm].
    force_n : float
        Applied force [N].
    thickness_mm : float
        Bone thickness under the burr [mm] (``inf``: no thin-bone rise).
    """
    params = np.array([1.0, speed_rpm, force_n, thickness_mm], dtype=np.float64)
    return float(_targets(params, _burr_vector(burr))[1])


# ------------------------------------------------------------------ kernel
@njit(cache=True, nogil=True, inline="always")
def _rand(rng):
    """Uniform in [-1, 1) from a xorshift64* generator (state ``rng[0]``)."""
    x = rng[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    rng[0] = x
    y = x * np.uint64(0x2545F4914F6CDD1D)
    return float(y >> np.uint64(11)) * (2.0 / 9007199254740992.0) - 1.0


@njit(cache=True, nogil=True)
def render_kernel(out, params, burr, state, phase, jit, rng, sample_rate):
    """Fill ``out`` with the next block of sound.

    Parameters
    ----------
    out : (n,) float32
        Receives the samples, in [-1, 1].
    params : (4,) float64
        Drill (>0.5 on), speed [rpm], force [N], thickness [mm]; read once.
    burr : (N_BURR,) float64
        Burr data (see :func:`_burr_vector`).
    state : (N_STATE,) float64
        Envelope, current fundamental [Hz], tone / noise / depth gains and
        the band-pass filter's memory; updated in place.
    phase : (MAX_PARTIALS,) float64
        Partial phases [cycles]; updated.
    jit : (MAX_PARTIALS,) float64
        Partial amplitude-noise states; updated.
    rng : (1,) uint64
        Noise generator state (non-zero); updated.
    sample_rate : float
        [Hz]
    """
    n = out.shape[0]
    if n == 0:
        return
    running, f0_t, level = _targets(params, burr)
    env0 = state[S_ENV]
    if not running and env0 <= 0.0:
        for q in range(n):
            out[q] = np.float32(0.0)
        state[S_ENV] = 0.0
        return
    fs = sample_rate
    # envelope: linear ramp toward 1 / 0 at the attack / decay rate
    if running:
        env1 = min(1.0, env0 + n / (fs * ATTACK_S))
    else:
        env1 = max(0.0, env0 - n / (fs * DECAY_S))
    if not running:
        f0_t = state[S_F0]               # hold the pitch while decaying
    tone_t = (1.0 - burr[B_NOISE]) * _LEVEL_TONE[level]
    noise_t = burr[B_NOISE] * _LEVEL_NOISE[level]
    depth_t = _LEVEL_DEPTH[level]
    if env0 <= 0.0:                      # starting from silence: no glide
        state[S_F0] = f0_t
        state[S_TONE] = tone_t
        state[S_NOISE] = noise_t
        state[S_DEPTH] = depth_t
    f0_0, tone0, noise0, depth0 = state[S_F0], state[S_TONE], state[S_NOISE], state[S_DEPTH]
    inv_n = 1.0 / n
    # partials: normalize by the amplitude sum
    n_part = int(burr[B_N_PARTIALS])
    a_sum = 0.0
    for k in range(n_part):
        a_sum += burr[B_AMP + k]
    a_norm = 1.0 / a_sum if a_sum > 0.0 else 0.0
    limit_hz = NYQUIST_FRACTION * 0.5 * fs
    # amplitude noise: one-pole low-pass, scaled to unit variance
    c = 1.0 - math.exp(-_TWO_PI * JITTER_HZ / fs)
    jit_scale = math.sqrt(3.0 * (2.0 - c) / c)
    # band-pass (constant 0 dB peak) for the block's end pitch, normalized
    # by its noise bandwidth (~ pi/2 * fc / Q) to about unit output RMS
    fc = min(NOISE_CENTRE * max(f0_t, 1.0), 0.45 * fs)
    w0 = _TWO_PI * fc / fs
    alpha = math.sin(w0) / (2.0 * NOISE_Q)
    a0 = 1.0 + alpha
    b0 = alpha / a0
    a1 = -2.0 * math.cos(w0) / a0
    a2 = (1.0 - alpha) / a0
    band_gain = math.sqrt(3.0 * 0.5 * fs / (0.5 * math.pi * fc / NOISE_Q))
    x1, x2, y1, y2 = state[S_X1], state[S_X2], state[S_Y1], state[S_Y2]
    for q in range(n):
        u = (q + 1) * inv_n
        env = env0 + (env1 - env0) * u
        f0 = f0_0 + (f0_t - f0_0) * u
        tone = tone0 + (tone_t - tone0) * u
        noise = noise0 + (noise_t - noise0) * u
        depth = depth0 + (depth_t - depth0) * u
        s = 0.0
        for k in range(n_part):
            f = burr[B_MULT + k] * f0
            p = phase[k] + f / fs
            p -= math.floor(p)
            phase[k] = p
            r = jit[k] + c * (_rand(rng) - jit[k])
            jit[k] = r
            if f < limit_hz:
                s += burr[B_AMP + k] * (1.0 + depth * jit_scale * r) * math.sin(_TWO_PI * p)
        x = _rand(rng)
        y = b0 * (x - x2) - a1 * y1 - a2 * y2
        x2 = x1
        x1 = x
        y2 = y1
        y1 = y
        v = OUTPUT_GAIN * env * (tone * a_norm * s + noise * band_gain * y)
        out[q] = np.float32(min(1.0, max(-1.0, v)))
    state[S_X1], state[S_X2], state[S_Y1], state[S_Y2] = x1, x2, y1, y2
    state[S_ENV] = env1
    state[S_F0] = f0_t
    state[S_TONE] = tone_t
    state[S_NOISE] = noise_t
    state[S_DEPTH] = depth_t


@njit(cache=True, nogil=True)
def _to_pcm16(block, out):
    """Float samples in [-1, 1] to 16-bit PCM (clipped, rounded)."""
    for q in range(block.shape[0]):
        v = min(1.0, max(-1.0, float(block[q]))) * 32767.0
        out[q] = np.int16(math.floor(v + 0.5))


def _splitmix64(x: int) -> int:
    """Scramble a seed into a well-mixed non-zero 64-bit state."""
    mask = (1 << 64) - 1
    x = (x + 0x9E3779B97F4A7C15) & mask
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
    x ^= x >> 31
    return x or 0x9E3779B97F4A7C15


def _burr_vector(burr) -> np.ndarray:
    """Pack the sound fields of a burr into the kernel's float64 vector."""
    partials = tuple(burr.sound_harmonics)
    if not 1 <= len(partials) <= MAX_PARTIALS:
        raise ValueError(f"a burr needs 1 to {MAX_PARTIALS} sound harmonics, "
                         f"got {len(partials)}")
    v = np.zeros(N_BURR)
    v[B_BASE_HZ] = burr.sound_base_hz
    v[B_HZ_PER_N] = burr.sound_force_hz_per_n
    v[B_NOISE] = burr.sound_noise
    v[B_LIGHT_N] = burr.sound_contact_light_n
    v[B_FIRM_N] = burr.sound_contact_firm_n
    v[B_THIN_MM] = burr.thin_bone_mm
    v[B_THIN_GAIN] = burr.thin_bone_gain
    v[B_DEFAULT_RPM] = burr.default_speed_rpm
    v[B_MAX_RPM] = burr.max_speed_rpm
    v[B_MAX_FORCE_N] = burr.max_force_n
    v[B_N_PARTIALS] = len(partials)
    for k, (m, a) in enumerate(partials):
        v[B_MULT + k] = m
        v[B_AMP + k] = a
    if not (np.isfinite(v).all() and v[B_BASE_HZ] > 0 and v[B_DEFAULT_RPM] > 0
            and v[B_THIN_MM] > 0 and 0 <= v[B_NOISE] <= 1):
        raise ValueError(f"burr {getattr(burr, 'name', burr)!r} has invalid sound data")
    return v


# -------------------------------------------------------------- synthesizer
class SoundSynth:
    """Block synthesizer of one burr's sound.

    Parameters
    ----------
    burr : Burr
        Reads the ``sound_*``, ``thin_bone_*``, speed and ``max_force_n``
        fields.
    sample_rate : int
        Output rate [Hz].
    seed : int
        Seed of the noise and of the partials' start phases.

    Attributes
    ----------
    params : (4,) float64
        What :meth:`set_params` writes (drill, speed [rpm], force [N],
        thickness [mm]); the renderer reads it once per block.
    """

    def __init__(self, burr, sample_rate: int = SAMPLE_RATE, seed: int = 0):
        sample_rate = int(sample_rate)
        if sample_rate < 8000:
            raise ValueError(f"sample_rate must be >= 8000 Hz, got {sample_rate}")
        self.sample_rate = sample_rate
        self.seed = int(seed)
        self.params = np.zeros(N_PARAMS)
        self.params[P_THICKNESS_MM] = math.inf
        self._burr = _burr_vector(burr)
        self.burr = burr
        self._state = np.zeros(N_STATE)
        self._phase = np.zeros(MAX_PARTIALS)
        self._jit = np.zeros(MAX_PARTIALS)
        self._rng = np.zeros(1, dtype=np.uint64)
        self.reset()

    def reset(self) -> None:
        """Silence and the seeded start state (parameters are kept)."""
        self._state[:] = 0.0
        self._phase[:] = np.random.default_rng(self.seed).random(MAX_PARTIALS)
        self._jit[:] = 0.0
        self._rng[0] = np.uint64(_splitmix64(self.seed & ((1 << 64) - 1)))

    def set_params(self, drill: bool, speed_rpm: float, force_n: float,
                   thickness_mm: float = math.inf) -> None:
        """Hand the current drill state to the audio side (cheap, lock-free).

        Parameters
        ----------
        drill : bool
            Drill running.
        speed_rpm : float
            Drill speed [rpm].
        force_n : float
            Applied force magnitude [N] (e.g. ``state.out[O_MAG]``).
        thickness_mm : float
            Bone thickness under the burr [mm]; ``inf`` (or NaN) when not in
            contact or unknown.
        """
        p = self.params
        p[P_SPEED_RPM] = speed_rpm
        p[P_FORCE_N] = force_n
        p[P_THICKNESS_MM] = thickness_mm
        p[P_DRILL] = 1.0 if drill else 0.0

    def set_burr(self, burr) -> None:
        """Switch to another burr's sound (takes effect at the next block;
        pitch and gains glide over that block)."""
        self._burr = _burr_vector(burr)        # one reference swap: atomic
        self.burr = burr

    def render(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` with the next block (no allocation).

        Parameters
        ----------
        out : (n,) float32
            Any 1-D float32 array (e.g. a column of a callback's buffer).

        Returns
        -------
        out
        """
        if out.dtype != np.float32 or out.ndim != 1:
            raise ValueError(f"out must be a 1-D float32 array, got {out.dtype} "
                             f"with shape {out.shape}")
        render_kernel(out, self.params, self._burr, self._state, self._phase, self._jit,
                      self._rng, float(self.sample_rate))
        return out

    @property
    def envelope(self) -> float:
        """Current envelope, 0 (silent) to 1."""
        return float(self._state[S_ENV])


def render_seconds(synth: SoundSynth, seconds: float, block: int = BLOCK) -> np.ndarray:
    """Render ``seconds`` of sound in blocks of ``block`` samples (analysis).

    Returns
    -------
    (n,) float32
        ``n = round(seconds * sample_rate)`` samples.
    """
    n = int(round(seconds * synth.sample_rate))
    out = np.zeros(n, dtype=np.float32)
    for q in range(0, n, block):
        synth.render(out[q:q + block])
    return out


# ------------------------------------------------------------------ output
class WavRecorder:
    """Write the rendered sound to a 16-bit mono PCM WAV file (``--wav FILE``).

    Parameters
    ----------
    path : str or Path
        Output file (overwritten).
    sample_rate : int
        [Hz], the synthesizer's rate.
    max_block : int
        Longest block :meth:`write` takes without reallocating its buffer.
    """

    def __init__(self, path, sample_rate: int = SAMPLE_RATE, max_block: int = 4096):
        self.path = Path(path)
        self.sample_rate = int(sample_rate)
        self.frames = 0
        self._pcm = np.zeros(max_block, dtype=np.int16)
        self._lock = threading.Lock()
        self._wav = wave.open(str(self.path), "wb")
        self._wav.setnchannels(1)
        self._wav.setsampwidth(2)
        self._wav.setframerate(self.sample_rate)

    def write(self, block: np.ndarray) -> None:
        """Append samples in [-1, 1] (clipped); thread-safe."""
        n = block.shape[0]
        with self._lock:
            if self._wav is None:
                return
            if n > self._pcm.shape[0]:
                self._pcm = np.zeros(n, dtype=np.int16)
            pcm = self._pcm[:n]
            _to_pcm16(block, pcm)
            self._wav.writeframesraw(pcm.tobytes())
            self.frames += n

    def close(self) -> None:
        """Finish the file (header sizes); idempotent."""
        with self._lock:
            if self._wav is not None:
                self._wav.close()
                self._wav = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class AudioOutput:
    """A running sounddevice stream (from :func:`open_output`)."""

    notice = None

    def __init__(self, stream):
        self.stream = stream

    def close(self) -> None:
        """Stop and close the stream; idempotent."""
        if self.stream is not None:
            try:
                self.stream.stop()
            finally:
                self.stream.close()
                self.stream = None


class SilentSink:
    """Stand-in for an audio device: renders blocks and drops them.

    A background thread renders (and hands to ``recorder``, if any) one block
    every ``block / sample_rate`` seconds when ``realtime`` is True, so the
    synthesizer and a WAV recording advance as they would with a device;
    with ``realtime`` False nothing is rendered.

    Attributes
    ----------
    notice : str or None
        Why no device is used (set by :func:`open_output`).
    """

    def __init__(self, synth: SoundSynth, block: int = BLOCK, recorder=None,
                 realtime: bool = True, notice: str | None = None):
        self.synth = synth
        self.block = int(block)
        self.recorder = recorder
        self.notice = notice
        self._stop = threading.Event()
        self._thread = None
        if realtime:
            self._thread = threading.Thread(target=self._run, name="bonesim-silent-audio",
                                            daemon=True)
            self._thread.start()

    def _run(self) -> None:
        buf = np.zeros(self.block, dtype=np.float32)
        period = self.block / self.synth.sample_rate
        due = time.perf_counter()
        while not self._stop.is_set():
            self.synth.render(buf)
            if self.recorder is not None:
                self.recorder.write(buf)
            due += period
            delay = due - time.perf_counter()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -0.5:               # fell far behind: do not race to catch up
                due = time.perf_counter()

    def close(self) -> None:
        """Stop the background thread; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None


def open_output(synth: SoundSynth, device=None, block: int = BLOCK, recorder=None,
                realtime_fallback: bool = True, say: bool = True):
    """Play the synthesizer on an audio device, or fall back to silence.

    Parameters
    ----------
    synth : SoundSynth
        Rendered from the audio callback (its only renderer from now on).
    device : int or str, optional
        sounddevice output device; default the system's.
    block : int
        Callback block length [samples].
    recorder : WavRecorder, optional
        Also receives every rendered block.
    realtime_fallback : bool
        Whether the silent fallback keeps rendering at real-time pace.
    say : bool
        Print the notice to stderr. False where the caller shows it itself (the
        simulator's HUD and run summary), so that it appears once.

    Returns
    -------
    AudioOutput or SilentSink
        Has ``.close()`` and ``.notice`` (None when a device plays; else the
        text, printed to stderr when ``say``). Never raises for a missing
        PortAudio library or device.
    """
    errors: tuple = (ImportError, OSError, ValueError)
    try:
        import sounddevice as sd        # lazy: PortAudio is loaded here only

        errors = errors + (sd.PortAudioError,)

        def callback(outdata, frames, time_info, status):
            col = outdata[:, 0]
            synth.render(col)
            if outdata.shape[1] > 1:
                outdata[:, 1:] = outdata[:, :1]
            if recorder is not None:
                recorder.write(col)

        stream = sd.OutputStream(samplerate=synth.sample_rate, blocksize=block,
                                 channels=1, dtype="float32", callback=callback,
                                 device=device)
        try:
            stream.start()
        except BaseException:
            stream.close()
            raise
        return AudioOutput(stream)
    except errors as exc:
        reason = str(exc).strip() or type(exc).__name__
        notice = (f"bonesim: no audio output ({reason}); the drill sound is muted"
                  + (f" and still recorded to {recorder.path}." if recorder is not None
                     else ". Use --wav FILE to record it."))
        if say:
            print(notice, file=sys.stderr, flush=True)
        return SilentSink(synth, block, recorder, realtime_fallback, notice)


def warmup() -> None:
    """Compile the sound kernels (cached on disk after the first run)."""
    from types import SimpleNamespace

    burr = SimpleNamespace(
        name="warmup", sound_base_hz=1000.0, sound_harmonics=((1.0, 1.0), (2.0, 0.5)),
        sound_noise=0.3, sound_force_hz_per_n=-50.0, sound_contact_light_n=0.05,
        sound_contact_firm_n=1.0, thin_bone_mm=2.0, thin_bone_gain=0.3,
        default_speed_rpm=60000.0, max_speed_rpm=80000.0, max_force_n=3.0)
    s = SoundSynth(burr, SAMPLE_RATE)
    s.set_params(True, 60000.0, 1.0, 1.0)
    buf = np.zeros((BLOCK, 2), dtype=np.float32)
    s.render(buf[:, 0])                          # strided (callback column)
    s.render(np.zeros(BLOCK, dtype=np.float32))  # contiguous
    _to_pcm16(buf[:, 0], np.zeros(BLOCK, dtype=np.int16))
    _to_pcm16(np.zeros(BLOCK, dtype=np.float32), np.zeros(BLOCK, dtype=np.int16))
    fundamental_hz(burr, 60000.0, 1.0)
