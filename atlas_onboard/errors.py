"""The one error hierarchy of atlas-onboard.

Every error a user can cause (a bad file, a bad argument, a bad message) is an ``AtlasError``; the CLI
turns it into one line on stderr and exit status 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


def read_failure(exc: OSError | UnicodeDecodeError) -> str:
    """Why a file could not be read, in a few words: the system's reason (``No such file or directory``)
    where there is one, else the exception's text (a file that is not UTF-8)."""
    return str((exc.strerror if isinstance(exc, OSError) else None) or exc)


class AtlasError(Exception):
    """Base of every error atlas-onboard raises on purpose."""


class ConfigError(AtlasError):
    """A world file or node setting is invalid; the message names the file, field path and problem."""

    def __init__(self, path: str, problem: str, file: str | None = None) -> None:
        self.path = path
        self.problem = problem
        self.file = file
        where = f"{file}: " if file else ""
        field = f"{path}: " if path else ""
        super().__init__(f"{where}{field}{problem}")


class GeometryError(AtlasError):
    """An array of the wrong shape or a value that is not a valid rotation/transform."""
