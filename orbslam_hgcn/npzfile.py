"""Versioned .npz files (vocabularies, maps, caches): atomic writes and checked reads.

Every read goes through :func:`read_npz` (no pickles; a missing, empty, truncated or corrupt
file raises the caller's error class naming the file), and files with a header through
:func:`read_versioned_npz` (magic string and format version checked).
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import OrbslamError


def atomic_save_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> Path:
    """Write ``arrays`` as an .npz at ``path`` via a temporary file and a rename.

    An exception (or Ctrl-C) during the write removes the temporary file and leaves any
    existing ``path`` untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            (np.savez_compressed if compress else np.savez)(fh, **arrays)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def read_npz(path: Path, what: str, error: type[OrbslamError]) -> dict[str, np.ndarray]:
    """All arrays of an .npz file, read eagerly; any damage is an ``error`` naming the file."""
    if not path.is_file():
        raise error(f"{path}: {what} file not found")
    if path.stat().st_size == 0:
        raise error(f"{path}: {what} file is empty")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as exc:
        raise error(f"{path}: not a readable {what} file (truncated or corrupt: {exc})") from None


def read_versioned_npz(
    path: Path, what: str, magic: str, version: int | tuple[int, ...], error: type[OrbslamError], rebuild_hint: str
) -> dict[str, np.ndarray]:
    """:func:`read_npz`, then the scalar ``_magic`` must equal ``magic`` and
    ``_format_version`` be ``version`` (or one of them); ``rebuild_hint`` ends the version
    error."""
    arrays = read_npz(path, what, error)
    found_magic = arrays.get("_magic")
    if found_magic is None or found_magic.shape != () or str(found_magic) != magic:
        raise error(f"{path}: not an orbslam_hgcn {what} file (no '{magic}' header)")
    versions = (version,) if isinstance(version, int) else tuple(version)
    found = arrays.get("_format_version")
    if found is None or found.shape != () or int(found) not in versions:
        shown = "none" if found is None else str(found)
        readable = " and ".join(str(v) for v in versions)
        raise error(f"{path}: {what} format version {shown} is not supported (this software reads version "
                    f"{readable}); {rebuild_hint}")
    return arrays
