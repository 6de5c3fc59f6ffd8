"""Where a recording goes: the ``--rerun`` argument and the three sinks (spawn, save, connect).

``spawn`` starts a native viewer and streams to it; ``save`` writes an ``.rrd`` file;
``connect`` streams to a running viewer or server over gRPC. Every mode works on a machine
without a display: when no viewer can be started or reached, the recording is saved to a
file instead and a warning says where.

Only :func:`attach_sink` imports the rerun SDK, so parsing the command line stays cheap.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import shutil
import socket
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from orbslam_hgcn.errors import ConfigError

if TYPE_CHECKING:
    import rerun as rr

log = logging.getLogger(__name__)

MODES = ("spawn", "save", "connect")
DEFAULT_PORT = 9876
DEFAULT_GRPC_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"
_SCHEMES = {"rerun": "rerun", "rerun+http": "rerun+http", "rerun+https": "rerun+https",
            "http": "rerun+http", "https": "rerun+https"}
_USAGE = "expected --rerun spawn | --rerun save FILE.rrd | --rerun connect [HOST:PORT or URL]"


def grpc_url(address: str) -> str:
    """Normalise a viewer address to the gRPC URL rerun expects.

    Accepts ``HOST:PORT``, ``PORT``, or a URL with scheme ``rerun``, ``rerun+http``,
    ``rerun+https`` (``http``/``https`` are read as ``rerun+http``/``rerun+https``) and an
    empty or ``/proxy`` path. Returns e.g. ``rerun+http://127.0.0.1:9876/proxy``.
    """
    addr = address.strip()
    if not addr:
        raise ConfigError(f"--rerun connect: empty address; {_USAGE}")
    if addr.isdigit():
        addr = f"127.0.0.1:{addr}"
    if "://" not in addr:
        addr = f"rerun+http://{addr}"
    parts = urlsplit(addr)
    scheme = _SCHEMES.get(parts.scheme.lower())
    if scheme is None:
        raise ConfigError(
            f"--rerun connect {address!r}: unknown scheme {parts.scheme!r}; use HOST:PORT or "
            "rerun+http://HOST:PORT/proxy"
        )
    try:
        port = parts.port
    except ValueError as exc:
        raise ConfigError(f"--rerun connect {address!r}: bad port ({exc})") from None
    if not parts.hostname:
        raise ConfigError(f"--rerun connect {address!r}: no host; use HOST:PORT")
    if parts.path not in ("", "/", "/proxy") or parts.query or parts.fragment:
        raise ConfigError(
            f"--rerun connect {address!r}: the path must be /proxy (rerun's gRPC endpoint)"
        )
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    default_port = 443 if scheme == "rerun+https" else DEFAULT_PORT
    return f"{scheme}://{host}:{port or default_port}/proxy"


def parse_rerun_arg(tokens: Sequence[str] | None) -> tuple[str, str | None]:
    """Parse the tokens of ``--rerun`` into ``(mode, target)``.

    ``spawn`` -> ("spawn", None); ``save FILE.rrd`` -> ("save", FILE.rrd);
    ``connect [ADDR]`` -> ("connect", gRPC URL, default ``DEFAULT_GRPC_URL``);
    a lone ``FILE.rrd`` is read as ``save FILE.rrd``. Raises ConfigError on anything else.
    """
    toks = [str(t) for t in (tokens or [])]
    if not toks:
        raise ConfigError(f"--rerun: missing mode; {_USAGE}")
    mode, rest = toks[0].lower(), toks[1:]
    if mode not in MODES and len(toks) == 1 and toks[0].lower().endswith(".rrd"):
        mode, rest = "save", toks
    if mode not in MODES:
        raise ConfigError(f"--rerun: unknown mode {toks[0]!r}; {_USAGE}")
    if mode == "spawn":
        if rest:
            raise ConfigError(f"--rerun spawn takes no argument, got {' '.join(rest)!r}; {_USAGE}")
        return "spawn", None
    if mode == "save":
        if len(rest) != 1:
            raise ConfigError(f"--rerun save needs exactly one FILE.rrd, got {len(rest)} arguments")
        path = Path(rest[0])
        if path.suffix.lower() != ".rrd":
            raise ConfigError(f"--rerun save {rest[0]!r}: the file name must end in .rrd")
        if path.is_dir():
            raise ConfigError(f"--rerun save {rest[0]!r}: is a directory, expected a FILE.rrd")
        folder = next((p for p in path.absolute().parents if p.exists()), None)
        if folder is not None and not folder.is_dir():
            raise ConfigError(f"--rerun save {rest[0]!r}: cannot be created: {folder} is a file")
        return "save", str(path)
    if len(rest) > 1:
        raise ConfigError(f"--rerun connect takes one address, got {' '.join(rest)!r}")
    return "connect", grpc_url(rest[0]) if rest else DEFAULT_GRPC_URL


def add_rerun_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--rerun MODE [TARGET]`` to a subcommand; read it with :func:`parse_rerun_arg`."""
    parser.add_argument(
        "--rerun", nargs="+", metavar="MODE", default=None,
        help="visualise in rerun: 'spawn' (start a viewer), 'save FILE.rrd', or "
        f"'connect [HOST:PORT]' (default {DEFAULT_GRPC_URL})",
    )


def viewer_executable() -> str | None:
    """Path of the rerun viewer binary (``RERUN_CLI_PATH``, the rerun-sdk wheel, or PATH)."""
    env = os.environ.get("RERUN_CLI_PATH")
    if env:
        return env if Path(env).is_file() else None
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.submodule_search_locations:
        exe = Path(next(iter(spec.submodule_search_locations))) / (
            "rerun.exe" if sys.platform.startswith("win") else "rerun"
        )
        if exe.is_file():
            return str(exe)
    return shutil.which("rerun")


def display_available() -> bool:
    """Whether a native window can be opened (Linux/BSD need an X11 or Wayland display)."""
    if sys.platform.startswith(("win", "darwin")):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def endpoint_reachable(url: str, timeout: float = 1.0) -> bool:
    """Whether a TCP connection to the host and port of a gRPC URL succeeds."""
    parts = urlsplit(url)
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout):
            return True
    except OSError:
        return False


def default_fallback_path(app_id: str) -> Path:
    """``./<app_id>-YYYYmmdd-HHMMSS.rrd``: where a recording goes when no viewer is there."""
    return Path.cwd() / f"{app_id}-{time.strftime('%Y%m%d-%H%M%S')}.rrd"


def _save(rec: rr.RecordingStream, path: str | Path, blueprint: Any) -> tuple[str, str]:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec.save(path, default_blueprint=blueprint)
    return "save", str(path)


def _spawn_problem(rec: rr.RecordingStream, port: int) -> str | None:
    """Why no viewer can be spawned here (None: try). Starts the viewer when possible."""
    import rerun as rr

    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if endpoint_reachable(url, timeout=0.2):
        return None  # a viewer already listens there: rerun reuses it
    if not display_available():
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    exe = viewer_executable()
    if exe is None:
        return "the rerun viewer binary was not found (install rerun-sdk, or set RERUN_CLI_PATH)"
    # rr.spawn waits until the viewer binds its port and never raises; a viewer that cannot
    # open its window binds, then exits. Probe the port after a short grace to tell.
    rr.spawn(port=port, connect=False, executable_path=exe, recording=rec)
    time.sleep(0.5)
    if not endpoint_reachable(url, timeout=1.0):
        return f"the viewer ({exe}) did not stay up on port {port}"
    return None


def attach_sink(
    rec: rr.RecordingStream,
    mode: str,
    target: str | None,
    *,
    blueprint: Any = None,
    fallback_path: str | Path | None = None,
    port: int = DEFAULT_PORT,
) -> tuple[str, str]:
    """Send ``rec`` to the sink of ``mode`` with ``blueprint`` as its default layout.

    mode "save": target is the .rrd path. mode "connect": target is a gRPC URL or
    HOST:PORT (None: the default URL). mode "spawn": target ignored; the viewer listens on
    ``port``. When spawn or connect cannot reach a viewer, the recording is saved to
    ``fallback_path`` (default :func:`default_fallback_path`) with a warning.
    Returns the (mode, target) actually used.
    """
    if mode not in MODES:
        raise ConfigError(f"rerun mode {mode!r}: expected one of {', '.join(MODES)}")
    app_id = str(rec.get_application_id() or "rerun")
    fallback = Path(fallback_path) if fallback_path is not None else default_fallback_path(app_id)
    if mode == "save":
        if not target:
            raise ConfigError("rerun save: no .rrd path given")
        return _save(rec, target, blueprint)
    if mode == "connect":
        url = grpc_url(target) if target else DEFAULT_GRPC_URL
        if endpoint_reachable(url):
            rec.connect_grpc(url, default_blueprint=blueprint)
            return "connect", url
        problem = f"no rerun viewer or server answers at {url}"
    else:
        problem = _spawn_problem(rec, port)
        if problem is None:
            url = f"rerun+http://127.0.0.1:{port}/proxy"
            rec.connect_grpc(url, default_blueprint=blueprint)
            return "spawn", url
    log.warning(
        "rerun %s: %s; saving the recording to %s instead (view it with: rerun %s)",
        mode, problem, fallback, fallback,
    )
    return _save(rec, fallback, blueprint)
