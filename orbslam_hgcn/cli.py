"""The ``orbslam-hgcn`` command: one entry point, one subcommand per user task.

Each subcommand has a ``_add_<name>(sub)`` function that declares its arguments and binds
a handler; the handler parses nothing itself and calls a typed function in the package.
User errors (:class:`OrbslamError`) print one line on stderr and exit with status 2;
Ctrl-C exits with status 130.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

from orbslam_hgcn import __version__
from orbslam_hgcn.errors import OrbslamError

log = logging.getLogger("orbslam_hgcn")

# Subcommand registrars, in the order ``--help`` lists them.
_REGISTRARS: list[Callable[[argparse._SubParsersAction], None]] = []


def subcommand(fn: Callable[[argparse._SubParsersAction], None]) -> Callable:
    """Decorator: register a function that adds one subparser (with ``set_defaults(func=...)``)."""
    _REGISTRARS.append(fn)
    return fn


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="orbslam-hgcn",
        description="Monocular ORB-SLAM-style visual SLAM with an HGCN visual vocabulary.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for registrar in _REGISTRARS:
        registrar(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except OrbslamError as exc:
        print(f"orbslam-hgcn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"orbslam-hgcn {args.command}: interrupted", file=sys.stderr)
        return 130


# --- Subcommands ------------------------------------------------------------------------
# Each block below adds one subcommand; handlers import their stage lazily so that
# ``orbslam-hgcn --help`` stays fast.
