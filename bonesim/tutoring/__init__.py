"""Haptic tutoring: the control law, the instructor's server, the trainee's
sources and servo (and its process).
"""

__all__: list[str] = []
