"""How the keyframes of the tracker reach local mapping and loop closing: in order on the
calling thread, or through worker threads as ORB-SLAM runs them.

Both runners offer the same small interface to :class:`~orbslam_hgcn.runtime.system.System`:
``mapping_idle()`` (the tracker's AcceptKeyFrames), ``submit(kf)``, ``optimising`` (an
optimisation is being solved), ``wait_for_points(timeout_s)`` (wait until every keyframe
handed over has its new points triangulated and fused), ``submitted``, ``release_points(n)`` and
``holding`` (see below), ``sync()`` (wait until every keyframe handed over is
processed), ``check()`` (re-raise a stage's failure) and ``close(drain)``.

:class:`ThreadedStages` (ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. III):

* local mapping and loop closing each run in a :class:`~.worker.Worker` thread fed by a
  queue; the mapper hands the keyframes it keeps to the loop closer's queue;
* every stage holds the map lock (:attr:`Map.lock`) per step, the tracker per frame; the
  local and global BA hold it only to cut their problem from the map and write the result
  back; global BA (gtsam, which holds the GIL) is solved in a child process
  (:class:`~orbslam_hgcn.backend.solver.ProcessSolver`) so the tracking thread keeps the GIL
  meanwhile, local BA by the compiled Schur solver in the mapping thread (it releases the
  GIL; in a process too with ``local_ba_process``);
* keyframe acceptance: local mapping accepts a keyframe when idle, or while its local BA
  runs, in which case the waiting keyframe aborts that BA (ORB-SLAM's ``InterruptBA``
  followed by the insertion on the next frame, in one step) once its robust iterations
  are done (``BackendConfig.local_ba_abort_robust``); a stop request (loop correction,
  shutdown) aborts it too;
* with ``hold_points`` (``threads.mapping_sync: points``) local mapping tells the tracker
  when a keyframe's new points are triangulated and fused (:attr:`LocalMapper.on_points`),
  solves its local BA, and holds before writing it back (:attr:`LocalMapper.before_changes`)
  until the tracker releases it (:meth:`ThreadedStages.release_points`), so that the frame
  after a keyframe is tracked against exactly those points, never against part of its
  local BA or culling, and the run does not depend on the timing of the threads (a
  keyframe handed over meanwhile does not cut that BA short); a pause, the shutdown or
  :meth:`ThreadedStages.sync` release it too;
* the loop closer pauses local mapping for the correction and for writing back the global
  BA (ORB-SLAM ``RequestStop`` / ``Release``): :meth:`ThreadedStages.pause_mapping` stops
  new keyframes, waits for the frame being tracked to hand over its keyframe
  (:meth:`ThreadedStages.handover`), lets local mapping map every keyframe it was given,
  and holds it still until released. A keyframe still waiting in the queue has no
  spanning-tree parent and no covisibility links yet, so a correction would leave it at
  its uncorrected pose; ORB-SLAM's local mapping likewise empties its queue before it stops.

Both runners take an optional ``series`` list: per keyframe local mapping finished, they
append (keyframe id, its frame, local mapping ms, local BA ms, ``time.time()``), the
mapper's own timings (:func:`note_mapped`; a run's ``series.npz``,
:mod:`orbslam_hgcn.runtime.results`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

from orbslam_hgcn.backend.solver import InProcessSolver, ProcessSolver
from orbslam_hgcn.map import KeyFrame
from orbslam_hgcn.runtime.worker import Worker, WorkerError

log = logging.getLogger(__name__)


class ActivityCounter:
    """Counts optimisations (and loop corrections) in flight and started, across threads,
    for the latency figures."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.running = 0
        self.started = 0
        self.busy_s = 0.0  # wall time with at least one optimisation in flight
        self._since = 0.0

    def enter(self) -> None:
        with self._lock:
            if self.running == 0:
                self._since = time.perf_counter()
            self.running += 1
            self.started += 1

    def exit(self) -> None:
        with self._lock:
            self.running -= 1
            if self.running == 0:
                self.busy_s += time.perf_counter() - self._since


class CountingSolver:
    """A solver proxy that records its calls in an :class:`ActivityCounter`."""

    def __init__(self, solver: Any, activity: ActivityCounter) -> None:
        self.solver = solver
        self.activity = activity

    def _run(self, name: str, *args: Any, **kw: Any) -> Any:
        self.activity.enter()
        try:
            return getattr(self.solver, name)(*args, **kw)
        finally:
            self.activity.exit()

    def local_ba(self, *args: Any, **kw: Any) -> Any:
        return self._run("local_ba", *args, **kw)

    def global_ba(self, *args: Any, **kw: Any) -> Any:
        return self._run("global_ba", *args, **kw)

    def essential_graph(self, *args: Any, **kw: Any) -> Any:
        return self._run("essential_graph", *args, **kw)

    def close(self) -> None:
        self.solver.close()


def note_mapped(series: list | None, mapper: Any, kf: KeyFrame) -> None:
    """Append to ``series`` (when given) the keyframe ``kf`` the mapper has just processed:
    (its id, its frame, local mapping ms, local BA ms, time.time())."""
    if series is None:
        return
    t = getattr(mapper, "timings", {})
    total, ba = t.get("total") or [float("nan")], t.get("local_ba") or [float("nan")]
    series.append((int(kf.id), int(getattr(kf, "frame_id", -1)), float(total[-1]), float(ba[-1]), time.time()))


class SequentialStages:
    """Local mapping, then loop closing, on the calling thread (deterministic)."""

    def __init__(self, mapper: Any, loop_closer: Any, series: list | None = None) -> None:
        self.mapper, self.loop_closer = mapper, loop_closer
        self.series = series
        self.activity = ActivityCounter()
        # The same in-process solves as without a runner, counted for the timing figures.
        mapper.solver = CountingSolver(InProcessSolver(), self.activity)
        if loop_closer is not None and hasattr(loop_closer, "solver"):
            loop_closer.solver = CountingSolver(InProcessSolver(), self.activity)

    @property
    def optimising(self) -> bool:
        return self.activity.running > 0

    def mapping_idle(self) -> bool:
        return True  # the mapper finished the previous keyframe already

    def mapping_done(self) -> bool:
        return True

    @contextlib.contextmanager
    def handover(self) -> Iterator[None]:
        """Nothing runs beside the tracker."""
        yield

    def wait_for_mapping(self, timeout_s: float, poll_s: float = 0.0, done: bool = False) -> bool:
        """Local mapping is idle already."""
        return True

    def wait_for_points(self, timeout_s: float) -> bool:
        """Every keyframe is mapped already."""
        return True

    submitted = 0  # nothing is held
    holding = False

    def release_points(self, n: int | None = None) -> bool:
        """Nothing is held."""
        return False

    def submit(self, kf: KeyFrame) -> None:
        out = self.mapper.process(kf)
        note_mapped(self.series, self.mapper, kf)
        if out is not None and self.loop_closer is not None:
            self.loop_closer.process(out)

    def sync(self) -> None:
        """Nothing is pending."""

    def check(self) -> None:
        """Stage errors are raised where they happen."""

    def close(self, drain: bool = True) -> None:
        """Nothing to stop."""


class ThreadedStages:
    """Local mapping and loop closing in worker threads (see the module text).

    process_solver: solve local and global BA in child processes (True), or in the worker
    threads themselves (False: simpler, but every gtsam iteration stalls tracking);
    local_ba_process: with process_solver, local BA by the compiled Schur solver in a process
    too (True), or in the mapping thread (False: it releases the GIL; ThreadsConfig's
    default); solver_nice: niceness added to those processes; worker_nice: to the worker
    threads (Linux); series: see the module text.
    """

    def __init__(
        self, mapper: Any, loop_closer: Any, process_solver: bool = True, solver_nice: int = 0, worker_nice: int = 0,
        series: list | None = None, local_ba_process: bool = True,
    ) -> None:  # fmt: skip
        self.mapper, self.loop_closer = mapper, loop_closer
        self.series = series
        self.activity = ActivityCounter()
        self._gate = threading.Lock()  # held by the mapper per keyframe, by a pause
        self._handover = threading.Lock()  # held by the tracker from its keyframe decision to the hand-over
        self._paused = False
        self._stopping = False
        # Keyframes handed to local mapping, how many of them have their new points
        # triangulated and fused (or were dropped before; wait_for_points), and how many
        # local mapping may carry on with past that (release_points; only with hold_points).
        self._points = threading.Condition()
        self._n_submitted = self._n_pointed = self._n_released = 0
        self._item_pointed = False  # of the keyframe being mapped (the mapping thread's)
        self.hold_points = False
        self.hold_timeout_s = 5.0  # a hold the tracker never releases ends after this
        self._solvers: list[Any] = []
        self._mapping: Worker | None = None
        self._loop: Worker | None = None
        self._process_solver = process_solver
        self._local_ba_process = local_ba_process
        self._solver_nice, self._worker_nice = solver_nice, worker_nice
        self._start()

    def _solver(self, name: str) -> Any:
        solver = ProcessSolver(name, nice=self._solver_nice) if self._process_solver else InProcessSolver()
        self._solvers.append(solver)
        return CountingSolver(solver, self.activity)

    def _start(self) -> None:
        # Local BA with the compiled solver runs in the mapping thread unless
        # threads.local_ba_process (it releases the GIL); in gtsam it needs a process.
        in_thread = not self._local_ba_process and getattr(self.mapper.backend, "local_ba_solver", "") == "schur"
        if in_thread:
            self.mapper.solver = CountingSolver(InProcessSolver(), self.activity)
        else:
            self.mapper.solver = self._solver("local-ba")
        if isinstance(self.mapper.solver.solver, ProcessSolver):
            self.mapper.solver.solver.start()  # loads in the child while tracking starts
        self.mapper.should_abort = self._abort_ba
        self.mapper.on_points, self.mapper.before_changes = self._pointed, self._hold
        self._mapping = Worker("mapping", self._map_one, nice=self._worker_nice).start()
        if self.loop_closer is not None:
            if hasattr(self.loop_closer, "pause_mapping"):
                self.loop_closer.pause_mapping = self.pause_mapping
            if hasattr(self.loop_closer, "solver"):
                self.loop_closer.solver = self._solver("global-ba")  # its process starts with the first loop
            self._loop = Worker("loop", self.loop_closer.process, nice=self._worker_nice).start()

    # --- the tracker's side --------------------------------------------------------------
    @property
    def optimising(self) -> bool:
        return self.activity.running > 0

    def mapping_idle(self) -> bool:
        """ORB-SLAM AcceptKeyFrames: idle, or solving a local BA that a new keyframe may abort."""
        w = self._mapping
        if w is None or self._paused or self._stopping:
            return False
        if not w.busy:
            return True
        return bool(self.mapper.in_ba) and w.pending == 0

    def mapping_done(self) -> bool:
        """Local mapping has finished every keyframe handed to it (nothing queued or running)."""
        w = self._mapping
        return w is not None and not w.busy and w.pending == 0

    def wait_for_mapping(self, timeout_s: float, poll_s: float = 0.002, done: bool = False) -> bool:
        """Wait until local mapping accepts a keyframe (:meth:`mapping_idle`: idle, or in
        a local BA that the next keyframe will cut short), or with ``done`` until it has
        finished every keyframe (:meth:`mapping_done`), at most ``timeout_s``; True when it
        does. Returns False at once during a pause or the shutdown."""
        deadline = time.perf_counter() + timeout_s
        ready = self.mapping_done if done else self.mapping_idle
        while not ready():
            if self._paused or self._stopping or time.perf_counter() >= deadline:
                return False
            self.check()
            time.sleep(poll_s)
        return True

    def wait_for_points(self, timeout_s: float) -> bool:
        """Wait until local mapping has triangulated and fused the new points of every
        keyframe handed to it (local BA and culling may still run), at most ``timeout_s``;
        True when it has. A keyframe that mapping skips or fails on counts as done."""
        deadline = time.perf_counter() + timeout_s
        with self._points:
            target = self._n_submitted
            while self._n_pointed < target and not self._stopping:
                self.check()  # a failed stage maps nothing more
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                self._points.wait(left)
            ok = self._n_pointed >= target
        self.check()
        return ok

    @property
    def submitted(self) -> int:
        """Keyframes handed to local mapping so far."""
        return self._n_submitted

    @property
    def holding(self) -> bool:
        """With hold_points: local mapping has made the new points of every keyframe handed
        to it and holds (or will hold) before the rest of its changes until released; it
        goes on to a new keyframe as soon as one is handed over."""
        with self._points:
            made = self._n_pointed == self._n_submitted
            return self.hold_points and made and self._n_released < self._n_pointed

    def release_points(self, n: int | None = None) -> bool:
        """Let local mapping carry on past the new points of the first ``n`` keyframes
        handed to it (None: all so far); True when that releases a keyframe not released
        before."""
        with self._points:
            n = self._n_submitted if n is None else min(n, self._n_submitted)
            if n <= self._n_released:
                return False
            self._n_released = n
            self._points.notify_all()
            return True

    def _pointed(self, kf: KeyFrame | None = None) -> None:
        """The keyframe being mapped has its new and fused points (LocalMapper.on_points),
        or its mapping ended before (``kf`` None)."""
        self._item_pointed = True
        with self._points:
            self._n_pointed += 1
            self._points.notify_all()

    def _hold(self, kf: KeyFrame) -> None:
        """LocalMapper.before_changes: with hold_points, wait until the keyframe being
        mapped is released or a later one is handed over (at most hold_timeout_s)."""
        if not (self.hold_points and self._item_pointed):
            return
        with self._points:
            k = self._n_pointed
            deadline = time.perf_counter() + self.hold_timeout_s
            while self._n_released < k and self._n_submitted <= k and not (self._paused or self._stopping):
                left = deadline - time.perf_counter()
                if left <= 0:
                    log.warning("keyframe %d: not released after its new points within %.1f s; mapping goes on",
                                kf.id, self.hold_timeout_s)
                    break
                self._points.wait(left)

    @contextlib.contextmanager
    def handover(self) -> Iterator[None]:
        """Held by the tracker around a frame's tracking and the hand-over of its keyframe,
        so that :meth:`pause_mapping` sees every keyframe the tracker decided on."""
        with self._handover:
            yield

    def submit(self, kf: KeyFrame) -> None:
        self.check()
        # A keyframe waiting in the queue is linked in the map already; keyframe culling of
        # the one being mapped must not remove it before its own insertion.
        self.mapper.map.set_not_erase(kf.id)
        with self._points:
            self._n_submitted += 1
            self._points.notify_all()  # a keyframe held after its new points goes on
        self._mapping.submit(kf)

    def _abort_ba(self) -> bool:
        """The mapper's should_abort: a keyframe waits, a pause or the shutdown is asked."""
        w = self._mapping
        return self._paused or self._stopping or (w is not None and w.pending > 0 and not self.hold_points)

    # --- the workers ---------------------------------------------------------------------
    def _map_one(self, kf: KeyFrame) -> None:
        self._item_pointed = False
        try:
            self._map_keyframe(kf)
        finally:
            if not self._item_pointed:
                self._pointed()

    def _map_keyframe(self, kf: KeyFrame) -> None:
        with self._gate:
            m = self.mapper.map
            m.set_erase(kf.id)
            if kf.bad:
                return
            try:
                out = self.mapper.process(kf)
            except (ValueError, KeyError) as exc:
                # The tracker may discard a small lost map (Atlas.drop, under the map lock)
                # between two steps of its keyframe's mapping: the rest of that work is moot.
                if not getattr(m, "dropped", False):
                    raise
                log.debug("keyframe %d: its map was discarded while it was being mapped (%s)", kf.id, exc)
                return
            note_mapped(self.series, self.mapper, kf)
        if out is not None and self._loop is not None:
            self._loop.submit(out)

    def pause_mapping(self, pause: bool) -> None:
        """True: stop new keyframes, map the ones handed over (a running local BA is cut
        short), then hold local mapping still. False: let it go on. Called by the loop
        closer's thread, which must not hold the map lock."""
        if pause:
            self._paused = True  # from now on the tracker makes no keyframe (mapping_idle)
            with self._handover:  # a frame that decided on one before has handed it over
                pass
            self.release_points()
            w = self._mapping
            if w is not None and not self._stopping:
                w.wait_idle()
            self._gate.acquire()
            self.activity.enter()  # a loop correction or write-back counts as optimising
        else:
            self.activity.exit()
            self._gate.release()
            self._paused = False

    # --- life cycle ----------------------------------------------------------------------
    def sync(self) -> None:
        """Wait until every keyframe handed over is mapped and loop-checked."""
        self.release_points()
        for w in (self._mapping, self._loop):
            if w is not None:
                w.wait_idle()

    def check(self) -> None:
        for w in (self._mapping, self._loop):
            if w is not None:
                w.check()

    def close(self, drain: bool = True) -> None:
        """Stop the workers (after the queued keyframes with ``drain``; a running BA is
        aborted either way), join them, stop the solver processes. The first stage error
        is raised after everything is stopped."""
        self._stopping = not drain
        self.release_points()
        error: BaseException | None = None
        try:
            for w in (self._mapping, self._loop):  # mapping first: it feeds the loop closer
                if w is None:
                    continue
                try:
                    w.stop(drain=drain and error is None)
                except WorkerError as exc:
                    error = error or exc
        finally:
            self._mapping = self._loop = None
            for s in self._solvers:
                s.close()
            self._solvers.clear()
            # The stages are plain classes again, solving in the calling thread.
            self.mapper.solver, self.mapper.should_abort = InProcessSolver(), None
            self.mapper.on_points = self.mapper.before_changes = None
            if self.loop_closer is not None:
                for attr in ("solver", "pause_mapping"):
                    if hasattr(self.loop_closer, attr):
                        setattr(self.loop_closer, attr, None)
        if error is not None:
            raise error
