"""The engine: the hashed voxel grid, the hybrid surface and its shading, the
haptic step (Model / State / step), event rings and materials. It imports
nothing above it.
"""

__all__: list[str] = []
