"""Build every kernel of a run ahead of time into one extension module (see
:mod:`orbslam_hgcn.aot`): ``python -m orbslam_hgcn.runtime.aot_build``, run by
``python -m orbslam_hgcn.runtime.kernels`` (and so by ``tools/setup.sh``) with the built
kernels turned off, so that numba compiles the originals.

The signatures are those of a run: every kernel module warms itself with the argument types
of a real run (:func:`orbslam_hgcn.runtime.kernels.warm_all`), and each signature numba
compiled there is exported. Each export calls numba's own kernel, compiled with its own
options (``fastmath`` included), so the built code computes what the JIT-compiled code
computes; the exported wrappers release the GIL, as ``nogil`` kernels do. The code is built
for this machine's CPU (as numba's JIT does). A C compiler is needed; without one the build
fails, says why, and runs use numba's cache.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from orbslam_hgcn import aot


def arg_spec(t: Any) -> str | None:
    """The manifest's spec of the numba type ``t`` (None: a type the built module does not
    take; that signature is left to numba)."""
    from numba.core import types
    from numba.np.numpy_support import as_dtype

    if isinstance(t, types.Array):
        if not t.aligned or t.layout not in ("C", "F", "A"):
            return None
        try:
            dtype = as_dtype(t.dtype)
        except NotImplementedError:
            return None
        if dtype.kind not in "biuf":
            return None
        return f"array:{dtype.name}:{t.ndim}:{t.layout}:{'w' if t.mutable else 'r'}"
    return {types.int64: "int64", types.float64: "float64", types.boolean: "bool"}.get(t)


def _trampoline(kernel: Any, n_args: int) -> Any:
    """A function of ``n_args`` arguments that calls ``kernel`` (numba compiles the kernel
    with its own options and links it into the export)."""
    names = ", ".join(f"a{i}" for i in range(n_args))
    env = {"_kernel": kernel}
    exec(f"def export({names}):\n    return _kernel({names})\n", env)  # noqa: S102 - fixed text
    return env["export"]


def kernels_of_a_run() -> dict[str, Any]:
    """Every numba kernel of the run's modules, qualified name -> dispatcher, after warming
    them all (which gives each the signatures of a run)."""
    from numba.core.registry import CPUDispatcher

    from orbslam_hgcn import compiled
    from orbslam_hgcn.runtime import kernels

    if compiled.BUILT is not None:
        raise RuntimeError(f"the built kernels are loaded in this process: set {aot.ENV_SWITCH}=0 to build them")
    kernels.warm_all()
    found = {}
    for name in (*kernels.RUN_KERNEL_MODULES, "orbslam_hgcn.compiled"):
        module = importlib.import_module(name)
        for value in vars(module).values():
            if isinstance(value, CPUDispatcher) and value.__module__ == name:
                found[f"{name}.{value.py_func.__qualname__}"] = value
    return found


def build(folder: Path) -> dict[str, Any]:
    """Compile the kernels of a run into ``folder`` (the extension module and its manifest,
    the manifest written last); returns the manifest."""
    import numba.pycc.compiler as pycc_compiler
    from numba.core.compiler import Flags
    from numba.pycc import CC

    found = kernels_of_a_run()

    class _ReleaseGil(Flags):  # the exports release the GIL, as the nogil kernels do
        def __init__(self, *args: Any, **kw: Any) -> None:
            super().__init__(*args, **kw)
            self.release_gil = True

    cc = CC(aot.MODULE_NAME)
    cc.target_cpu = "host"
    cc.verbose = False
    exported: dict[str, list[list[Any]]] = {}
    sources = set()
    for qualname, kernel in sorted(found.items()):
        sources.add(sys.modules[kernel.__module__].__file__)
        for sig in kernel.signatures:
            specs = [arg_spec(t) for t in sig]
            if any(s is None for s in specs):
                continue
            symbol = f"k{sum(len(v) for v in exported.values())}"
            cc.export(symbol, kernel.overloads[sig].signature)(_trampoline(kernel, len(sig)))
            exported.setdefault(qualname, []).append([symbol, specs])
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder, prefix=".build-") as tmp:
        cc.output_dir = tmp
        saved = pycc_compiler.Flags
        pycc_compiler.Flags = _ReleaseGil
        try:
            cc.compile()
        finally:
            pycc_compiler.Flags = saved
        (built,) = Path(tmp).glob(aot.MODULE_NAME + "*")
        manifest = {
            "format": aot.FORMAT,
            **aot.runtime_id(),
            "numba": numba_version(),
            "sources": {str(Path(f).resolve().relative_to(aot.PACKAGE_ROOT)): aot.source_hash(Path(f))
                        for f in sorted(sources)},  # fmt: skip
            "kernels": exported,
        }
        manifest_tmp = Path(tmp) / aot.MANIFEST
        manifest_tmp.write_text(json.dumps(manifest, indent=1) + "\n")
        (folder / aot.MANIFEST).unlink(missing_ok=True)
        os.replace(built, folder / built.name)
        os.replace(manifest_tmp, folder / aot.MANIFEST)
    return manifest


def remove(folder: Path) -> None:
    """Remove the build in ``folder`` (its manifest first), nothing else."""
    (folder / aot.MANIFEST).unlink(missing_ok=True)
    for path in folder.glob(aot.MODULE_NAME + "*"):
        path.unlink()


def numba_version() -> str:
    import numba

    return numba.__version__


# Run with the build in place: every kernel of a run comes from it, numba is never imported.
_VERIFY = """
import sys
from orbslam_hgcn import aot, compiled
from orbslam_hgcn.runtime import kernels
assert compiled.BUILT is not None, aot.status
kernels.warm_all()
assert not aot.fallbacks, aot.fallbacks
assert not any(m == "numba" or m.startswith("numba.") for m in sys.modules), "numba imported"
print("ok")
"""


def verify(folder: Path) -> str | None:
    """Why the build in ``folder`` fails a run's warm-up in a fresh process (None: it
    passes: every kernel from the build, numba not imported)."""
    env = {**os.environ, aot.ENV_DIR: str(folder)}
    env.pop(aot.ENV_SWITCH, None)
    r = subprocess.run([sys.executable, "-c", _VERIFY], env=env, capture_output=True, text=True, timeout=600)
    if r.returncode == 0 and r.stdout.strip().endswith("ok"):
        return None
    return (r.stderr.strip().splitlines() or ["no output"])[-1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orbslam_hgcn.runtime.aot_build", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="folder of the build (default: the first of "
                        "orbslam_hgcn.aot.build_dirs(): the package's _aot folder, or the user's cache)")  # fmt: skip
    args = parser.parse_args(argv)
    folder = args.out or aot.build_dirs()[0]
    t0 = time.perf_counter()
    try:
        manifest = build(folder)
    except Exception as exc:  # noqa: BLE001 - any failure of the build (no C compiler, ...) is reported
        print(f"building the kernels ahead of time failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    why = verify(folder)
    if why is not None:
        remove(folder)
        print(f"the kernels built ahead of time failed their check and were removed: {why}", file=sys.stderr)
        return 1
    n = sum(len(v) for v in manifest["kernels"].values())
    print(f"built {n} kernel signatures ahead of time in {time.perf_counter() - t0:.0f} s into {folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
