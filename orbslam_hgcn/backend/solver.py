"""Where the optimisations run: in the calling thread, or in a persistent child process.

gtsam's Python bindings keep the GIL while they iterate, so a local BA run by a mapping
thread freezes the tracking thread for as long as an iteration lasts (hundreds of ms on a
large window). :class:`ProcessSolver` runs the optimisations in a child process started
with the ``spawn`` method (safe with threads, unlike ``fork``): the problem goes through a
pipe as numpy arrays, the optimised arrays come back, and the calling thread meanwhile
waits on the pipe, which releases the GIL. :class:`InProcessSolver` calls the same
functions directly (the sequential system). Both offer one interface:

* ``local_ba(problem, config, cpu_budget_s, should_stop) -> (BAResult, budget_hit)``
* ``global_ba(problem, iterations, config, should_stop) -> BAResult``
* ``essential_graph(S_cw, edges, S_ji, fixed, weights, config) -> (K, 4, 4) S_cw``
* ``close()``

``should_stop`` is polled between LM iterations (ORB-SLAM's abort flag). In the child it
is a shared event that the waiting thread raises when its callback turns True; the CPU
budget of local BA is measured on the thread that runs the solve, in either place.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

from orbslam_hgcn.backend.bundle_adjustment import (
    BAProblem,
    BAResult,
    global_bundle_adjustment,
    local_bundle_adjustment,
)
from orbslam_hgcn.config import BackendConfig

log = logging.getLogger(__name__)

StopFn = Callable[[], bool] | None


class SolverError(RuntimeError):
    """The optimiser process failed (an exception in it, or it died); the message carries
    the child's traceback."""


class InProcessSolver:
    """Run every optimisation in the calling thread."""

    def local_ba(
        self, p: BAProblem, config: BackendConfig, cpu_budget_s: float = 0.0, should_stop: StopFn = None
    ) -> tuple[BAResult, bool]:
        """ORB-SLAM local BA of ``p``, stopped when the calling thread has used
        ``cpu_budget_s`` of CPU time (0: no cap) or ``should_stop`` says so.
        Returns (result, whether the CPU budget stopped it)."""
        deadline = time.thread_time() + cpu_budget_s

        def over_budget() -> bool:
            return cpu_budget_s > 0 and time.thread_time() > deadline

        def stop() -> bool:
            return over_budget() or (should_stop is not None and bool(should_stop()))

        res = local_bundle_adjustment(*p, config, should_stop=stop)
        return res, over_budget()

    def global_ba(self, p: BAProblem, iterations: int, config: BackendConfig, should_stop: StopFn = None) -> BAResult:
        """ORB-SLAM global BA of ``p`` (``iterations`` LM iterations, Huber kernel)."""
        return global_bundle_adjustment(*p, iterations=iterations, config=config, should_stop=should_stop)

    def essential_graph(
        self, S_cw: np.ndarray, edges: np.ndarray, S_ji: np.ndarray, fixed: np.ndarray,
        weights: np.ndarray | None = None, config: BackendConfig | None = None,
    ) -> np.ndarray:  # fmt: skip
        """Sim(3) essential-graph optimisation (see :func:`.pose_graph.optimize_essential_graph`)."""
        from orbslam_hgcn.backend.pose_graph import optimize_essential_graph

        return optimize_essential_graph(S_cw, edges, S_ji, fixed, weights, config)

    def close(self) -> None:
        """Nothing to release."""


def _serve(conn: Any, abort: Any) -> None:
    """Child process loop: answer ``(op, args)`` requests until ``None`` or a closed pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    solver = InProcessSolver()
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        op, args = msg
        try:
            if op == "ping":
                reply: tuple = ("ok", "pong")
            elif op in ("local_ba", "global_ba"):
                reply = ("ok", getattr(solver, op)(*args, should_stop=abort.is_set))
            elif op == "essential_graph":
                reply = ("ok", solver.essential_graph(*args))
            else:
                raise ValueError(f"unknown optimiser request {op!r}")
        except Exception as exc:  # noqa: BLE001 - sent to the parent, which raises SolverError
            reply = ("error", f"{type(exc).__name__}: {exc}", traceback.format_exc())
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return  # the parent went away


class ProcessSolver:
    """Run the optimisations in one persistent child process (``spawn`` start method).

    The process starts on :meth:`start` or the first request and lives until
    :meth:`close`; one request at a time (callers from several threads queue on a lock).
    poll_s: how often the waiting thread looks at ``should_stop`` and at the child's health.
    """

    def __init__(self, name: str = "optimiser", poll_s: float = 0.005) -> None:
        self.name = name
        self.poll_s = poll_s
        self._ctx = mp.get_context("spawn")
        self._lock = threading.Lock()
        self._proc: Any = None
        self._conn: Any = None
        self._abort: Any = None
        self.requests = 0

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def start(self) -> ProcessSolver:
        """Start the child process (no-op when it runs)."""
        with self._lock:
            self._start()
        return self

    def _start(self) -> None:
        if self.alive:
            return
        self._close_locked()
        parent, child = self._ctx.Pipe()
        self._abort = self._ctx.Event()
        self._proc = self._ctx.Process(
            target=_serve, args=(child, self._abort), name=f"orbslam-{self.name}", daemon=True
        )
        self._proc.start()
        child.close()
        self._conn = parent
        log.debug("%s process started (pid %d)", self.name, self._proc.pid)

    def ping(self) -> None:
        """Round trip to the child: returns once it has started and imported gtsam."""
        self._call("ping", (), None)

    def local_ba(
        self, p: BAProblem, config: BackendConfig, cpu_budget_s: float = 0.0, should_stop: StopFn = None
    ) -> tuple[BAResult, bool]:
        """As :meth:`InProcessSolver.local_ba`, solved in the child process."""
        return self._call("local_ba", (p, config, cpu_budget_s), should_stop)

    def global_ba(self, p: BAProblem, iterations: int, config: BackendConfig, should_stop: StopFn = None) -> BAResult:
        """As :meth:`InProcessSolver.global_ba`, solved in the child process."""
        return self._call("global_ba", (p, iterations, config), should_stop)

    def essential_graph(
        self, S_cw: np.ndarray, edges: np.ndarray, S_ji: np.ndarray, fixed: np.ndarray,
        weights: np.ndarray | None = None, config: BackendConfig | None = None,
    ) -> np.ndarray:  # fmt: skip
        """As :meth:`InProcessSolver.essential_graph`, solved in the child process."""
        return self._call("essential_graph", (S_cw, edges, S_ji, fixed, weights, config), None)

    def _call(self, op: str, args: tuple, should_stop: StopFn) -> Any:
        with self._lock:
            self._start()
            self._abort.clear()
            try:
                if should_stop is not None and should_stop():
                    self._abort.set()
                self._conn.send((op, args))
                # Waiting on the pipe releases the GIL; between waits, forward a stop request
                # and notice a dead child.
                while not self._conn.poll(self.poll_s):
                    if not self._proc.is_alive():
                        raise SolverError(f"{self.name} process died (exit code {self._proc.exitcode}) during {op}")
                    if should_stop is not None and not self._abort.is_set() and should_stop():
                        self._abort.set()
                reply = self._conn.recv()
            except SolverError:
                self._close_locked()
                raise
            except (EOFError, OSError) as exc:
                code = self._proc.exitcode if self._proc is not None else None
                self._close_locked()
                raise SolverError(f"{self.name} process lost during {op} (exit code {code})") from exc
            except BaseException:
                # Interrupted while waiting (Ctrl-C, a failing callback): the reply would be
                # out of step with the next request, so the process is replaced.
                self._close_locked()
                raise
            self.requests += 1
            if reply[0] == "ok":
                return reply[1]
            raise SolverError(f"{self.name} process: {op} failed: {reply[1]}\n--- in the child process ---\n{reply[2]}")

    def close(self, timeout: float = 5.0) -> None:
        """Stop the child process and wait for it (terminated if it does not exit in time)."""
        with self._lock:
            self._close_locked(timeout)

    def _close_locked(self, timeout: float = 5.0) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if self._abort is not None:
            self._abort.set()  # a solve still running stops at its next iteration
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        if proc is not None:
            proc.join(timeout)
            if proc.is_alive():
                log.warning("%s process did not stop in %.0f s; terminating it", self.name, timeout)
                proc.terminate()
                proc.join(timeout)
        if conn is not None:
            conn.close()

    def __enter__(self) -> ProcessSolver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
