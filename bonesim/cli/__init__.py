"""The ``bonesim`` command line.
"""

__all__: list[str] = []
