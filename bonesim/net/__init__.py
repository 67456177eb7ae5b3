"""The network: authenticated UDP packets and keys, the tutoring wire protocol,
the nerve monitor's server and remote console.
"""

__all__: list[str] = []
