"""Output paths checked before any work starts: a command that writes a folder or a file
says at once, as one OrbslamError, when it cannot (a path under a file, no permission)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from orbslam_hgcn.errors import OrbslamError


def check_output_folder(out: str | Path, what: str = "--out") -> Path:
    """The output folder ``out``, checked before a run starts, without creating it: an
    existing folder must be writable; a new one must have a writable folder as its nearest
    existing ancestor. An OrbslamError names the problem."""
    p = Path(out).expanduser()
    if p.exists() and not p.is_dir():
        raise OrbslamError(f"{p}: {what} names an existing file, not a folder")
    _check_writable(_nearest_existing(p), p, what)
    return p


def check_output_file(path: str | Path, what: str) -> Path:
    """A file to write at the end of a run (``--save-map``), checked before it starts: not
    a folder, and its folder can be created and written."""
    p = Path(path).expanduser()
    if p.is_dir():
        raise OrbslamError(f"{p}: {what} names a folder, not a file")
    _check_writable(_nearest_existing(p.parent), p, what)
    return p


def _nearest_existing(p: Path) -> Path:
    p = p.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_writable(folder: Path, target: Path, what: str) -> None:
    if not folder.is_dir():
        raise OrbslamError(f"{target}: {what} cannot be created: {folder} is a file")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise OrbslamError(f"{target}: {what} cannot be written ({folder}: {exc.strerror})") from None


def cache_root() -> Path:
    """The package's cache folder: ``$ORBSLAM_HGCN_CACHE``, else ``~/.cache/orbslam_hgcn``
    (rendered demo sequences, the kernels built for a read-only install, ORB's test pattern)."""
    env = os.environ.get("ORBSLAM_HGCN_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "orbslam_hgcn"
