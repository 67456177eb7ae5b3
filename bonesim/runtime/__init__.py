"""Processes that run live: shared memory and the process base, the 1 kHz
haptic loop, audio, the session recorder, the nerve monitor, headless runs.
"""

__all__: list[str] = []
