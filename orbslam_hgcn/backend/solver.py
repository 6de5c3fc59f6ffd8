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
import time

import numpy as np

from orbslam_hgcn.backend.bundle_adjustment import global_bundle_adjustment, local_bundle_adjustment
from orbslam_hgcn.backend.problem import BAProblem, BAResult
from orbslam_hgcn.childprocess import ChildProcess, StopFn
from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.errors import StageError

log = logging.getLogger(__name__)


class SolverError(StageError):
    """The optimiser process failed (an exception in it, or it died: ``lost``); the message
    names the process (``local-ba``, ``global-ba``) and carries the child's traceback."""

    stage = "optimiser process"


class InProcessSolver:
    """Run every optimisation in the calling thread. The compiled local BA kernels are
    loaded (or compiled) when it is built, before the first keyframe."""

    def __init__(self) -> None:
        from orbslam_hgcn.backend.schur_ba import warm_up

        warm_up()

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


class ProcessSolver:
    """Run the optimisations in one persistent child process
    (:class:`~orbslam_hgcn.childprocess.ChildProcess` serving an :class:`InProcessSolver`).

    The process starts on :meth:`start` or the first request and lives until
    :meth:`close`; one request at a time (callers from several threads queue on a lock).
    poll_s: how often the waiting thread looks at ``should_stop`` and at the child's health;
    nice: lowers the child's CPU priority (see :class:`~orbslam_hgcn.childprocess.ChildProcess`).
    """

    def __init__(self, name: str = "optimiser", poll_s: float = 0.005, nice: int = 0) -> None:
        self.name = name
        self._child = ChildProcess(name, InProcessSolver, (), SolverError, poll_s, nice)

    @property
    def alive(self) -> bool:
        return self._child.alive

    @property
    def requests(self) -> int:
        return self._child.requests

    def start(self) -> ProcessSolver:
        """Start the child process (no-op when it runs)."""
        self._child.start()
        return self

    def ping(self) -> None:
        """Round trip to the child: returns once it has started and imported gtsam."""
        self._child.call("ping")

    def local_ba(
        self, p: BAProblem, config: BackendConfig, cpu_budget_s: float = 0.0, should_stop: StopFn = None
    ) -> tuple[BAResult, bool]:
        """As :meth:`InProcessSolver.local_ba`, solved in the child process."""
        return self._child.call("local_ba", (p, config, cpu_budget_s), should_stop, stoppable=True)

    def global_ba(self, p: BAProblem, iterations: int, config: BackendConfig, should_stop: StopFn = None) -> BAResult:
        """As :meth:`InProcessSolver.global_ba`, solved in the child process."""
        return self._child.call("global_ba", (p, iterations, config), should_stop, stoppable=True)

    def essential_graph(
        self, S_cw: np.ndarray, edges: np.ndarray, S_ji: np.ndarray, fixed: np.ndarray,
        weights: np.ndarray | None = None, config: BackendConfig | None = None,
    ) -> np.ndarray:  # fmt: skip
        """As :meth:`InProcessSolver.essential_graph`, solved in the child process."""
        return self._child.call("essential_graph", (S_cw, edges, S_ji, fixed, weights, config))

    def kill(self) -> None:
        """Kill the child process at once (a lost process is reported by the next request)."""
        self._child.kill()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the child process and wait for it (terminated if it does not exit in time)."""
        self._child.close(timeout)

    def __enter__(self) -> ProcessSolver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
