"""Recorded sessions: reading (damaged files too), replaying bit for bit,
playback and video.
"""

__all__: list[str] = []
