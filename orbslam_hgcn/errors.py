"""The single error root of the package.

Every error caused by user input (missing files, malformed lines, bad calibration, an empty
or corrupt vocabulary, ...) is raised as an :class:`OrbslamError` (or a subclass) with a
message that names the file, and the line or key where it applies. The command-line
interface prints such errors as one line and exits with status 2, never with a traceback.

A failure while a run goes (a stage's worker thread raising, a child process failing or
dying) is a :class:`StageError` naming the stage; a frame that cannot be read is a
:class:`FrameError`. ``orbslam-hgcn run`` still writes the results of the frames processed
before either, and exits with its own status (see ``orbslam-hgcn run --help``).
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


class FrameError(DatasetError):
    """A frame of a sequence cannot be used: its file is missing, empty, truncated or
    corrupt, or its image has the wrong size. ``frame``: its index in the sequence."""

    def __init__(self, message: str, frame: int = -1) -> None:
        super().__init__(message)
        self.frame = frame


class StageError(OrbslamError):
    """A stage of a run failed: its worker thread raised, or its child process (bundle
    adjustment, ORB extraction) reported an error or died. ``stage`` names it; ``lost``:
    the child process died (killed, crashed) rather than reporting an error."""

    stage = "a stage"

    def __init__(self, message: str, *, stage: str | None = None, lost: bool = False) -> None:
        super().__init__(message)
        if stage is not None:
            self.stage = stage
        self.lost = lost


class Terminated(KeyboardInterrupt):
    """The process was asked to stop (SIGTERM): a run ends as on Ctrl-C, with its results."""


def where(path: str | Path, line: int | None = None, key: str | None = None) -> str:
    """Format a location for an error message: ``file``, ``file:line`` or ``file [key]``."""
    loc = str(path)
    if line is not None:
        loc += f":{line}"
    if key is not None:
        loc += f" [{key}]"
    return loc
