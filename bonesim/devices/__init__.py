"""Haptic and input devices: one interface, its backends.
"""

__all__: list[str] = []
