"""The compiled kernels built ahead of time: one extension module, loaded without numba.

``python -m orbslam_hgcn.runtime.kernels`` (run by ``tools/setup.sh``) compiles every
kernel of a run with numba's ahead-of-time compiler into one extension module for this
machine's CPU, beside a manifest (:mod:`orbslam_hgcn.runtime.aot_build`). A run then loads
that module in under a millisecond instead of importing numba and loading its cache (about
0.5 s per process: numba's import and its first use).

The module is used only while it matches: the manifest records the hash of every source
file whose kernels it holds, the CPU it was built for, the Python and numpy versions; any
difference (a kernel edited, the folder copied to another machine) and the run uses numba
as before, saying why at debug level. ``ORBSLAM_HGCN_AOT=0`` turns it off.

Each kernel is a :class:`Kernel`: it checks its arguments against the types it was built
for (dtype, dimensions, C order, alignment, writability; exact scalar types) and calls the
built function, which releases the GIL as numba's ``nogil`` kernels do. Arguments of any
other type go to numba, compiled (or loaded from its cache) on that first call, so a kernel
never runs on data it was not built for. This module imports only the standard library,
numpy and :mod:`orbslam_hgcn.outputs`.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import platform
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from orbslam_hgcn.outputs import cache_root

log = logging.getLogger(__name__)

FORMAT = 1
MODULE_NAME = "_orbslam_hgcn_kernels"
MANIFEST = "kernels.json"
ENV_SWITCH = "ORBSLAM_HGCN_AOT"
ENV_DIR = "ORBSLAM_HGCN_AOT_DIR"  # one folder for the build, instead of build_dirs()'s two
PACKAGE_ROOT = Path(__file__).resolve().parent

# Why the built module is not used in this process (None: it is, or nothing was looked for).
status: str | None = None
# Kernels called from Python with arguments their built versions do not take (each went to
# numba): qualified name -> the argument types of the first such call.
fallbacks: dict[str, str] = {}


def build_dirs() -> list[Path]:
    """Where the built module may be: inside the package (when it can be written) and the
    user's cache folder (for a read-only install); the first is where a build goes.
    ``ORBSLAM_HGCN_AOT_DIR`` names one folder instead."""
    if os.environ.get(ENV_DIR):
        return [Path(os.environ[ENV_DIR])]
    cache = cache_root() / "aot"
    key = hashlib.sha256(str(PACKAGE_ROOT).encode()).hexdigest()[:12]
    dirs = [PACKAGE_ROOT / "_aot", cache / key]
    if not os.access(PACKAGE_ROOT, os.W_OK):
        dirs.reverse()
    return dirs


def cpu_id() -> str:
    """This machine's CPU: architecture, model and instruction-set flags (Linux's
    /proc/cpuinfo), which the built code may use."""
    parts = [platform.machine()]
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            seen = set()
            for line in fh:
                key = line.split(":", 1)[0].strip()
                if key in ("model name", "flags", "Features", "CPU part") and key not in seen:
                    seen.add(key)
                    parts.append(line.strip())
                if not line.strip() and seen:
                    break
    except OSError:
        parts.append(platform.processor())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def runtime_id() -> dict[str, Any]:
    """What the built module depends on besides its sources: Python, numpy's major version,
    the CPU."""
    return {
        "python": list(sys.version_info[:2]),
        "numpy": np.__version__.split(".")[0],
        "cpu": cpu_id(),
    }


def source_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _stale(manifest: dict[str, Any]) -> str | None:
    """Why ``manifest`` does not describe this machine and these sources (None: it does)."""
    if manifest.get("format") != FORMAT:
        return "built by another version of the builder"
    here = runtime_id()
    for key, text in (("python", "Python"), ("numpy", "numpy"), ("cpu", "CPU")):
        if manifest.get(key) != here[key]:
            return f"built for another {text}"
    for rel, digest in manifest.get("sources", {}).items():
        path = PACKAGE_ROOT / rel
        if not path.is_file() or source_hash(path) != digest:
            return f"orbslam_hgcn/{rel} changed since it was built"
    return None


class Built:
    """The loaded extension module and its manifest."""

    def __init__(self, module: Any, manifest: dict[str, Any], folder: Path) -> None:
        self.module = module
        self.manifest = manifest
        self.folder = folder

    def exports(self, qualname: str) -> list[tuple[int, Callable[..., bool], Callable[..., Any]]]:
        """(number of arguments, argument check, built function) of each signature built for
        ``qualname``."""
        return [(len(specs), make_check(tuple(specs)), getattr(self.module, symbol))
                for symbol, specs in self.manifest["kernels"].get(qualname, [])]  # fmt: skip


def turned_off() -> bool:
    """Whether ``ORBSLAM_HGCN_AOT`` turns the built kernels off (0, no, off, false)."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "no", "off", "false")


def load() -> Built | None:
    """The built kernels when they match this machine and these sources, else None (the
    reason in :data:`status`)."""
    global status
    if turned_off():
        status = f"turned off ({ENV_SWITCH}=0)"
        return None
    reasons = []
    for folder in build_dirs():
        path = folder / MANIFEST
        if not path.is_file():
            continue
        try:
            manifest = json.loads(path.read_text())
            why = _stale(manifest)
        except (OSError, ValueError, AttributeError) as exc:
            why = f"unreadable manifest ({exc})"
        if why is None:
            so = folder / (MODULE_NAME + importlib.machinery.EXTENSION_SUFFIXES[0])
            try:
                spec = importlib.util.spec_from_file_location(MODULE_NAME, so)
                if spec is None or spec.loader is None:
                    raise ImportError(f"no loader for {so}")
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
            except (ImportError, OSError) as exc:
                why = f"{so.name} does not load ({exc})"
            else:
                status = None
                return Built(module, manifest, folder)
        reasons.append(f"{folder}: {why}")
    status = "; ".join(reasons) if reasons else "not built yet: python -m orbslam_hgcn.runtime.kernels builds it"
    log.debug("kernels built ahead of time not used: %s", status)
    return None


def numba_kernel(func: Callable[..., Any], options: dict[str, Any]) -> Any:
    """numba's compiled ``func`` with the kernels' settings: cached on disk, without the GIL,
    and ``options`` (numba imported here, at the first need)."""
    import numba

    return numba.njit(cache=True, nogil=True, **options)(func)


# Argument specs, as the builder writes them: "int64", "float64", "bool" for scalars and
# "array:<dtype>:<ndim>:<layout>:<r|w>" for arrays (layout C, F or A; r: read-only allowed).
_SCALARS = {
    "int64": "(type({a}) is int or type({a}) is _i8)",
    "float64": "(type({a}) is float or type({a}) is _f8)",
    "bool": "(type({a}) is bool or type({a}) is _b)",
}
_LAYOUT = {"C": "_f.c_contiguous and ", "F": "_f.f_contiguous and ", "A": ""}


@functools.lru_cache(maxsize=None)
def make_check(specs: tuple[str, ...]) -> Callable[..., bool]:
    """A function of ``len(specs)`` arguments that is True when they have the types
    ``specs`` (those numba would type them as, for the built signature)."""
    names = [f"a{i}" for i in range(len(specs))]
    terms = []
    env: dict[str, Any] = {"_nd": np.ndarray, "_i8": np.int64, "_f8": np.float64, "_b": np.bool_}
    for i, (a, spec) in enumerate(zip(names, specs)):
        if spec in _SCALARS:
            terms.append(_SCALARS[spec].format(a=a))
            continue
        parts = spec.split(":")
        if len(parts) != 5 or parts[0] != "array" or parts[3] not in _LAYOUT or parts[4] not in ("r", "w"):
            raise ValueError(f"unknown argument spec {spec!r}")
        _, dtype, ndim, layout, mode = parts
        env[f"_d{i}"] = np.dtype(dtype)
        writable = "" if mode == "r" else " and _f.writeable"
        terms.append(
            f"(type({a}) is _nd and ({a}.dtype is _d{i} or {a}.dtype == _d{i}) and {a}.ndim == {int(ndim)} "
            f"and (_f := {a}.flags).aligned and {_LAYOUT[layout]}True{writable})"
        )
    body = " and ".join(terms) or "True"
    src = f"def check({', '.join(names)}):\n    return {body}\n"
    exec(compile(src, f"<check {specs}>", "exec"), env)  # noqa: S102 - generated from the manifest's specs
    return env["check"]


def _describe(args: tuple[Any, ...]) -> str:
    out = []
    for a in args:
        if isinstance(a, np.ndarray):
            layout = "C" if a.flags.c_contiguous else ("F" if a.flags.f_contiguous else "A")
            out.append(f"array({a.dtype}, {a.ndim}d, {layout}{'' if a.flags.writeable else ', read-only'})")
        else:
            out.append(type(a).__name__)
    return ", ".join(out)


class Kernel:
    """A kernel whose built versions are called when the arguments fit one of them; numba's
    (created, compiled or loaded on first need) otherwise, and whenever numba compiles a
    kernel that calls this one."""

    def __init__(self, func: Callable[..., Any], options: dict[str, Any],
                 exports: list[tuple[int, Callable[..., bool], Callable[..., Any]]]) -> None:  # fmt: skip
        functools.update_wrapper(self, func)
        self.py_func = func
        self.options = options
        self.exports = exports
        self._dispatcher: Any = None

    @property
    def qualname(self) -> str:
        return f"{self.py_func.__module__}.{self.py_func.__qualname__}"

    @property
    def numba_used(self) -> bool:
        """Whether numba's version of this kernel was needed in this process."""
        return self._dispatcher is not None

    @property
    def dispatcher(self) -> Any:
        """numba's dispatcher of this kernel (numba imported at the first need)."""
        if self._dispatcher is None:
            self._dispatcher = numba_kernel(self.py_func, self.options)
        return self._dispatcher

    @property
    def _numba_type_(self) -> Any:
        # numba types a global kernel by this attribute: a kernel compiled by numba calls
        # this one through numba's dispatcher.
        return self.dispatcher._numba_type_

    def __call__(self, *args: Any) -> Any:
        n = len(args)
        for n_args, check, func in self.exports:
            if n == n_args and check(*args):
                return func(*args)
        if self.qualname not in fallbacks:
            fallbacks[self.qualname] = _describe(args)
            log.debug("%s: no version built for (%s); numba compiles or loads one", self.qualname, fallbacks[self.qualname])
        return self.dispatcher(*args)
