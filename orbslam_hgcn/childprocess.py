"""A persistent child process that answers method calls on one object.

Used where Python work must not share the GIL with tracking: gtsam keeps the GIL while it
iterates (bundle adjustment, :mod:`orbslam_hgcn.backend.solver`), and ORB extraction has
Python parts between its OpenCV calls (:mod:`orbslam_hgcn.runtime.extraction`).

The child is started with the ``spawn`` method (safe with threads, unlike ``fork``) and
builds its object as ``factory(*factory_args)`` (both must pickle). A request is a method
name and its arguments, sent through a pipe; the calling thread waits on the pipe, which
releases the GIL, and between waits it forwards a stop request (a shared event the method
gets as ``should_stop`` when the call is ``stoppable``) and notices a child that died. An
exception in the child comes back as ``error_type`` (a
:class:`~orbslam_hgcn.errors.StageError` naming the process) with the child's traceback;
the child stays up for the next request. A child that died is reported as ``error_type``
with ``lost=True`` by the request that finds it dead; it is replaced (as one interrupted
mid-request) on the next.

Signals: Ctrl-C (SIGINT) and SIGTERM are the parent's to handle. A child ignores SIGINT,
and defers SIGTERM by ``term_grace_s``: a SIGTERM sent to the whole process group (``kill
-- -PGID``, ``timeout``, a service manager) reaches the parent and its children at once;
the parent then ends its run as on Ctrl-C and stops its children itself, which exit
cleanly within the grace. A SIGTERM sent to a child alone ends it after the grace, and the
parent replaces it as any lost child. While the parent is stopping (:func:`stopping`,
set by the command line's SIGTERM handler) a child that dies is reported as ended by the
stop, and none is started again.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import threading
import traceback
from collections.abc import Callable
from typing import Any

from orbslam_hgcn.errors import StageError

log = logging.getLogger(__name__)

StopFn = Callable[[], bool] | None

# How long a child outlives a SIGTERM (see the module text): time for its parent, stopping
# on the same signal, to finish the keyframes handed to mapping and close it.
TERM_GRACE_S = 10.0

# Set while this process stops on a signal (the command line's SIGTERM handler): its
# children are not started again, and one that dies is not reported as lost.
_stopping = threading.Event()


def set_stopping(on: bool = True) -> None:
    """Say that this process is stopping (``on``) or no longer (a command that ended)."""
    if on:
        _stopping.set()
    else:
        _stopping.clear()


def stopping() -> bool:
    """Whether this process is stopping (:func:`set_stopping`)."""
    return _stopping.is_set()


def _defer_sigterm(grace_s: float) -> None:
    """In a child: on SIGTERM, exit by SIGTERM only ``grace_s`` later, unless the parent
    closes the child before."""

    def handler(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends it at once
        timer = threading.Timer(grace_s, os.kill, (os.getpid(), signal.SIGTERM))
        timer.daemon = True  # a child the parent closes meanwhile exits without waiting
        timer.start()

    signal.signal(signal.SIGTERM, handler)


def _serve(
    conn: Any, abort: Any, factory: Callable[..., Any], factory_args: tuple, nice: int,
    term_grace_s: float = TERM_GRACE_S, ready: Any = None,
) -> None:  # fmt: skip
    """Child process loop: answer ``(method, args, stoppable)`` requests until ``None`` or a
    closed pipe; ``ready`` (an event) is set once the object is built."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    _defer_sigterm(term_grace_s)  # so is a SIGTERM sent to the process group
    if nice > 0 and hasattr(os, "nice"):
        os.nice(nice)  # where the parent could not (see ChildProcess._start)
    obj = factory(*factory_args)
    if ready is not None:
        ready.set()
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        op, args, stoppable = msg
        try:
            if op == "ping":
                reply: tuple = ("ok", "pong")
            elif op.startswith("_") or not callable(getattr(obj, op, None)):
                raise ValueError(f"unknown request {op!r}")
            else:
                method = getattr(obj, op)
                reply = ("ok", method(*args, should_stop=abort.is_set) if stoppable else method(*args))
        except Exception as exc:  # noqa: BLE001 - sent to the parent, which raises error_type
            reply = ("error", f"{type(exc).__name__}: {exc}", traceback.format_exc())
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return  # the parent went away


class ChildProcess:
    """One persistent child serving ``factory(*factory_args)``; one request at a time
    (callers from several threads queue on a lock).

    name: names the process (``orbslam-<name>``) and the errors (their ``stage``);
    error_type: a StageError class, raised for a failed request or a lost child; poll_s:
    how often the waiting thread looks at ``should_stop`` and at the child's health; nice:
    added to the child's niceness (lower CPU priority) where the platform has ``os.nice``;
    term_grace_s: how long the child outlives a SIGTERM (see the module text).
    """

    def __init__(
        self,
        name: str,
        factory: Callable[..., Any],
        factory_args: tuple = (),
        error_type: type[StageError] = StageError,
        poll_s: float = 0.005,
        nice: int = 0,
        term_grace_s: float = TERM_GRACE_S,
    ) -> None:
        self.name = name
        self.nice = int(nice)
        # What the child adds to its own niceness: nothing where the parent sets it (os.setpriority).
        self._child_nice = 0 if hasattr(os, "setpriority") else self.nice
        self.term_grace_s = float(term_grace_s)
        self.factory, self.factory_args = factory, factory_args
        self.error_type = error_type
        self.poll_s = poll_s
        self._ctx = mp.get_context("spawn")
        self._lock = threading.Lock()
        self._proc: Any = None
        self._conn: Any = None
        self._abort: Any = None
        self._ready: Any = None
        self.requests = 0

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def starting(self) -> bool:
        """Started and alive, but its object not built yet (importing, loading kernels): a
        request now would wait for that. Does not block."""
        return self.alive and self._ready is not None and not self._ready.is_set()

    def start(self) -> ChildProcess:
        """Start the child (no-op when it runs)."""
        with self._lock:
            self._start()
        return self

    def _renice(self, pid: int) -> None:
        """Add ``nice`` to the new child's niceness from here (Linux and other Unixes)."""
        if self.nice <= 0 or self._child_nice > 0:  # nothing to add, or the child adds it
            return
        try:
            os.setpriority(os.PRIO_PROCESS, pid, min(19, os.getpriority(os.PRIO_PROCESS, 0) + self.nice))
        except (AttributeError, OSError):
            pass  # the child will not know: see _child_nice

    def _start(self) -> None:
        if self.alive:
            return
        self._close_locked()
        parent, child = self._ctx.Pipe()
        self._abort, self._ready = self._ctx.Event(), self._ctx.Event()
        proc = self._ctx.Process(
            target=_serve,
            args=(child, self._abort, self.factory, self.factory_args, self._child_nice, self.term_grace_s,
                  self._ready),
            name=f"orbslam-{self.name}", daemon=True,
        )  # fmt: skip
        try:
            # The niceness is given by the parent as soon as the child exists (_renice), so
            # that its start-up (imports, compiled kernels: about a second of CPU) already
            # yields to this process; the child adds it itself only where that failed.
            proc.start()
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        self._proc, self._conn = proc, parent
        self._renice(proc.pid)
        log.debug("%s process started (pid %d)", self.name, self._proc.pid)

    def call(self, op: str, args: tuple = (), should_stop: StopFn = None, stoppable: bool = False) -> Any:
        """``op(*args)`` on the child's object (with ``should_stop=`` when ``stoppable``);
        returns its result. Raises ``error_type`` when it fails or the child is lost."""
        with self._lock:
            if self._proc is not None and not self._proc.is_alive():
                code = self._proc.exitcode
                self._close_locked()
                raise self._lost(f"died (exit code {code}) before {op}")
            if stopping() and not self.alive:
                raise self._error(f"{self.name} process not started for {op}: this process is stopping", lost=True)
            self._start()
            self._abort.clear()
            try:
                if should_stop is not None and should_stop():
                    self._abort.set()
                self._conn.send((op, args, stoppable))
                while not self._conn.poll(self.poll_s):
                    if not self._proc.is_alive():
                        raise self._lost(f"died (exit code {self._proc.exitcode}) during {op}")
                    if should_stop is not None and not self._abort.is_set() and should_stop():
                        self._abort.set()
                reply = self._conn.recv()
            except self.error_type:
                self._close_locked()
                raise
            except (EOFError, OSError) as exc:
                code = self._proc.exitcode if self._proc is not None else None
                self._close_locked()
                raise self._lost(f"lost during {op} (exit code {code})") from exc
            except BaseException:
                # Interrupted while waiting (Ctrl-C, a failing callback): the reply would be
                # out of step with the next request, so the process is replaced.
                self._close_locked()
                raise
            self.requests += 1
            if reply[0] == "ok":
                return reply[1]
            raise self._error(
                f"{self.name} process: {op} failed: {reply[1]}\n--- in the child process ---\n{reply[2]}"
            )

    def _error(self, message: str, lost: bool = False) -> StageError:
        return self.error_type(message, stage=f"{self.name} process", lost=lost)

    def _lost(self, what: str) -> StageError:
        """The error of a child that died: ``what`` happened to it (and why, when this
        process is stopping)."""
        why = "; this process is stopping: not started again" if stopping() else ""
        return self._error(f"{self.name} process {what}{why}", lost=True)

    def kill(self) -> None:
        """Kill the child at once (tests use it to check that a lost child is reported)."""
        if self._proc is not None:
            self._proc.kill()
            self._proc.join()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the child and wait for it (terminated if it does not exit in time)."""
        with self._lock:
            self._close_locked(timeout)

    def _close_locked(self, timeout: float = 5.0) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if self._abort is not None:
            self._abort.set()  # a stoppable request still running stops at its next check
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        if proc is not None:
            proc.join(timeout)
            if proc.is_alive():  # killed: a child outlives a SIGTERM (term_grace_s)
                log.warning("%s process did not stop in %.0f s; killing it", self.name, timeout)
                proc.kill()
                proc.join(timeout)
        if conn is not None:
            conn.close()

    def __enter__(self) -> ChildProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
