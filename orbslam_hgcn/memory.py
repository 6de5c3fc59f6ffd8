"""Memory checks made before a big allocation: the memory available (``MemAvailable`` of
``/proc/meminfo``, else ``os.sysconf``), or the limit in megabytes given by the environment
variable ``ORBSLAM_HGCN_MEMORY_LIMIT_MB`` or by the caller, against an estimate; a command
that would not fit stops with an :class:`OrbslamError` naming the way out, before it
allocates anything.
"""

from __future__ import annotations

import os

from orbslam_hgcn.errors import OrbslamError

LIMIT_ENV = "ORBSLAM_HGCN_MEMORY_LIMIT_MB"


def available_bytes(limit_mb: float | None = None) -> int | None:
    """Memory the process may use: ``limit_mb`` if given, else ``$ORBSLAM_HGCN_MEMORY_LIMIT_MB``,
    else ``MemAvailable`` of ``/proc/meminfo``, else the free pages of ``os.sysconf``; None
    when none of them is known."""
    if limit_mb is None:
        env = os.environ.get(LIMIT_ENV, "").strip()
        if env:
            try:
                limit_mb = float(env)
            except ValueError:
                raise OrbslamError(f"{LIMIT_ENV}={env!r}: not a number of megabytes") from None
    if limit_mb is not None:
        return int(limit_mb * 2**20)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return None


def format_bytes(n: float) -> str:
    if n >= 2**30:
        return f"{n / 2**30:.1f} GiB"
    return f"{n / 2**20:.0f} MiB"


def check_memory(needed: int, what: str, way_out: str, *, limit_mb: float | None = None) -> None:
    """An OrbslamError when ``needed`` bytes exceed the memory available (see
    :func:`available_bytes`); the message names both and ``way_out``."""
    avail = available_bytes(limit_mb)
    if avail is not None and needed > avail:
        raise OrbslamError(
            f"{what} needs about {format_bytes(needed)} of memory but {format_bytes(avail)} is available; {way_out}"
        )
