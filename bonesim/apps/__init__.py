"""Applications: the interactive simulator and the headless showcase.
"""

__all__: list[str] = []
