"""Errors raised for bad user input.

Every problem with a file the user gave us (a case manifest, a volume, a burr,
a trajectory) is raised as a :class:`BonesimError` whose message names the
file (and, where it applies, the field, row or packet) and says what is wrong.
The command-line interface prints these as one line, never as a traceback.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["BonesimError", "ProcessFailed", "EXIT_ERROR", "EXIT_RECORDING_LOST"]

#: Exit status of a command stopped by a :class:`BonesimError` (one line on stderr).
EXIT_ERROR = 2
#: Exit status of a run that went to its end but whose recording did not: the
#: writer died, a write failed or the disk filled (one line on stderr says
#: what the file keeps, and up to when).
EXIT_RECORDING_LOST = 3


class BonesimError(Exception):
    """A clear, user-facing error about an input.

    Parameters
    ----------
    message : str
        What is wrong, in one sentence.
    path : str or Path, optional
        The file or folder the problem is in.
    field : str, optional
        The field, key, column or row inside that file.
    """

    def __init__(self, message: str, path: str | Path | None = None,
                 field: str | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.field = field
        where = ""
        if self.path is not None:
            where = str(self.path)
            if field:
                where += f" [{field}]"
            where += ": "
        elif field:
            where = f"[{field}]: "
        super().__init__(where + message)


class ProcessFailed(BonesimError):
    """A child process (:mod:`bonesim.runtime.child`) failed to start or run.

    Parameters
    ----------
    process : str
        The process's name (``bonesim-recorder``, ...).
    message : str
        What the child reported, or how it failed (died, timed out).
    """

    def __init__(self, process: str, message: str):
        super().__init__(message)
        self.process = process
        self.args = (f"{process}: {message}",)

    def __str__(self) -> str:
        return self.args[0]
