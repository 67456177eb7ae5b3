"""Recorded sessions, below the processes that record them: the file format
(:mod:`~bonesim.session.schema`, :mod:`~bonesim.session.header`,
:mod:`~bonesim.session.writer`, :mod:`~bonesim.session.disk_guard`), reading
it (damaged files and schema 1 too: :mod:`~bonesim.session.reader`), and what
is built on it: replaying bit for bit, playback and video, vision datasets.
"""

__all__: list[str] = []
