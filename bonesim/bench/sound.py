"""Audio benchmark behind ``bonesim bench``: block render time vs real time.

A block of ``BLOCK`` samples at ``SAMPLE_RATE`` must be rendered well within
its own duration (256 / 48000 s = 5.33 ms), or the callback underruns and
the sound clicks. ``audio_rtf_p99`` is the 99th percentile of the time one
:meth:`bonesim.sound.drill.SoundSynth.render` call takes divided by the block's
duration (target <= 0.1). The parameters change before every block, as the
haptic loop would change them (sweeping force through all contact levels,
speed, thickness, and the drill switching off and on), so the ramps and the
filter updates are always exercised.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["BLOCK", "SAMPLE_RATE", "bench_audio"]

#: Block length [samples] and rate [Hz] of the benchmark.
BLOCK = 256
SAMPLE_RATE = 48000


def bench_audio(quick: bool = False) -> dict:
    """Time :meth:`SoundSynth.render` on 256-sample blocks at 48 kHz.

    Parameters
    ----------
    quick : bool
        2 000 blocks (~11 s of sound) instead of 20 000 (~107 s).

    Returns
    -------
    dict
        ``{"audio_rtf_p99": {"value": ratio, "unit": "ratio", ...detail}}``
        with the p50 / p99 / max block times [us] and the block duration.
    """
    from bonesim.io.burrs import load_burr
    from bonesim.sound.drill import SoundSynth, warmup

    warmup()
    burrs = [load_burr("cutting-5mm"), load_burr("diamond-3mm")]
    synth = SoundSynth(burrs[0], SAMPLE_RATE, seed=1)
    n = 2000 if quick else 20000
    buf = np.zeros(BLOCK, dtype=np.float32)
    rng = np.random.default_rng(0)
    force = np.abs(np.cumsum(rng.normal(0.0, 0.05, n))) % 3.3      # wandering [N]
    speed = 40000.0 + 20000.0 * np.sin(np.arange(n) * 0.01)         # [rpm]
    thick = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0.0, 3.0, n))   # [mm]
    drill = (np.arange(n) // 400) % 5 != 4                          # off 1 block in 5 x 400
    ns = np.empty(n, dtype=np.int64)
    perf = time.perf_counter_ns
    for q in range(n):
        if q and q % 5000 == 0:
            synth.set_burr(burrs[(q // 5000) % 2])
        synth.set_params(bool(drill[q]), float(speed[q]), float(force[q]), float(thick[q]))
        t0 = perf()
        synth.render(buf)
        ns[q] = perf() - t0
    block_us = BLOCK / SAMPLE_RATE * 1e6
    us = ns / 1e3
    p50, p99 = (float(np.percentile(us, p)) for p in (50, 99))
    return {
        "audio_rtf_p99": {"value": round(p99 / block_us, 5), "unit": "ratio",
                          "target": 0.1, "block": BLOCK, "sample_rate": SAMPLE_RATE,
                          "blocks": n, "block_us": round(block_us, 2),
                          "render_p50_us": round(p50, 2), "render_p99_us": round(p99, 2),
                          "render_max_us": round(float(us.max()), 2)},
    }


if __name__ == "__main__":  # pragma: no cover
    import json

    print(json.dumps(bench_audio(), indent=2))
