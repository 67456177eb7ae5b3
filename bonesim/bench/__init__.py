"""Benchmarks behind ``bonesim bench``.
"""

__all__: list[str] = []
