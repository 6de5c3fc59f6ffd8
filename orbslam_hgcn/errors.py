"""The single error root of the package.

Every error caused by user input (missing files, malformed lines, bad calibration, an empty
or corrupt vocabulary, ...) is raised as an :class:`OrbslamError` (or a subclass) with a
message that names the file, and the line or key where it applies. The command-line
interface prints such errors as one line and exits with status 2, never with a traceback.
"""

from __future__ import annotations

from pathlib import Path


class OrbslamError(Exception):
    """An error the user can act on: the message says what is wrong and where."""


class ConfigError(OrbslamError):
    """A configuration or calibration file is missing, malformed or out of range."""


class DatasetError(OrbslamError):
    """A dataset folder, listing or image is missing, empty, unreadable or malformed."""


class VocabularyError(OrbslamError):
    """A vocabulary file is missing, truncated, corrupt, empty or of the wrong kind."""


def where(path: str | Path, line: int | None = None, key: str | None = None) -> str:
    """Format a location for an error message: ``file``, ``file:line`` or ``file [key]``."""
    loc = str(path)
    if line is not None:
        loc += f":{line}"
    if key is not None:
        loc += f" [{key}]"
    return loc
