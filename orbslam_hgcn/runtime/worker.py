"""One small generic worker: runs any stage's entry method on items taken from a queue.

Stages are plain classes with one entry (``process(keyframe)``, ``detect(keyframe)``) and
no thread code; a :class:`Worker` owns the thread. It stops on an event, never by
sleep-polling, and an exception raised by the stage reaches the caller: the worker stops
taking work and the next :meth:`Worker.submit`, :meth:`Worker.check` or :meth:`Worker.stop`
re-raises it.
"""

from __future__ import annotations

import logging
import os
import queue
import sys
import threading
from collections.abc import Callable
from typing import Any

from orbslam_hgcn.errors import StageError

log = logging.getLogger(__name__)

_STOP = object()


class WorkerError(StageError):
    """A stage raised inside its worker thread (``stage``: the worker's name); ``__cause__``
    holds the original exception."""


def lower_thread_priority(nice: int) -> None:
    """Add ``nice`` to the calling thread's niceness (Linux gives every thread its own;
    elsewhere, or when refused, nothing changes)."""
    if not (sys.platform.startswith("linux") and hasattr(os, "setpriority")):
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice, 19))
    except OSError as exc:
        log.debug("could not lower the priority of thread %d: %s", tid, exc)


class Worker:
    """Run ``handler(item)`` for each submitted item in a background thread, in order;
    ``nice`` lowers the thread's CPU priority (Linux)."""

    def __init__(self, name: str, handler: Callable[[Any], None], maxsize: int = 0, nice: int = 0) -> None:
        self.name = name
        self.nice = int(nice)
        self._handler = handler
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"orbslam-{name}", daemon=True)
        self._started = False

    def start(self) -> Worker:
        self._thread.start()
        self._started = True
        return self

    @property
    def pending(self) -> int:
        """Items waiting in the queue (not counting the one being processed)."""
        return self._queue.qsize()

    @property
    def busy(self) -> bool:
        """True while an item is being processed or items are waiting."""
        return not self._idle.is_set() or not self._queue.empty()

    def submit(self, item: Any) -> None:
        """Queue an item; blocks while a bounded queue is full. Re-raises a stage error."""
        self.check()
        self._idle.clear()
        while True:
            try:
                self._queue.put(item, timeout=0.5)
                return
            except queue.Full:
                self.check()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every queued item is processed (or the worker failed)."""
        self._queue.join()
        ok = self._idle.wait(timeout)
        self.check()
        return ok

    def check(self) -> None:
        """Re-raise, in the caller's thread, an exception the stage raised."""
        if self._error is not None:
            err = self._error
            lines = str(err).splitlines()  # a child process's error carries its traceback
            lost = isinstance(err, StageError) and err.lost
            raise WorkerError(
                f"{self.name} worker failed: {type(err).__name__}: {lines[0] if lines else ''}", stage=self.name,
                lost=lost,
            ) from err

    def stop(self, drain: bool = True) -> None:
        """Stop the thread and join it. With ``drain``, finish queued items first."""
        if self._started and self._thread.is_alive():
            if not drain:
                self._stop.set()
                self._discard_queue()
            self._queue.put(_STOP)
            self._thread.join()
        self.check()

    def _discard_queue(self) -> None:
        while True:
            try:
                self._queue.get_nowait()
                self._queue.task_done()
            except queue.Empty:
                return

    def _run(self) -> None:
        if self.nice > 0:
            lower_thread_priority(self.nice)
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if self._stop.is_set() or self._error is not None:
                    continue
                self._handler(item)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller by check()
                log.error("%s worker: %r", self.name, exc)
                self._error = exc
            finally:
                self._queue.task_done()
                if self._queue.empty():
                    self._idle.set()
