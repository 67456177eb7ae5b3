"""Physics beside the engine: bone dust, vibration, drill sound, monitor clicks
and rings, clearance, visibility, the sight line.
"""

__all__: list[str] = []
