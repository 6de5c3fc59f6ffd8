"""A re-entrant map lock that lets the tracking thread go first.

The threaded system shares one :class:`~orbslam_hgcn.map.Map` between tracking, local
mapping and loop closing, each holding ``Map.lock`` per frame or per step. With a plain
``threading.RLock`` a stage that releases the lock between two steps takes it straight back
(it still holds the GIL), so a waiting tracker can sit through several steps in a row.
:class:`TrackingFirstLock` has the same interface (``acquire``/``release``, context
manager, re-entrant) plus :meth:`TrackingFirstLock.acquire_first`: while a thread waits
that way, other threads' new acquisitions wait behind it, so the tracker waits for at most
the step in progress. Re-entrant acquisitions by the owner never wait.
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)


class TrackingFirstLock:
    """Re-entrant lock with a priority acquisition (see the module text)."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._owner: int | None = None
        self._count = 0
        self._first_waiting = 0

    def acquire(self, blocking: bool = True, timeout: float = -1, first: bool = False) -> bool:
        """Take the lock (re-entrant). ``first``: go before threads acquiring normally."""
        me = threading.get_ident()
        with self._cond:
            if self._owner == me:
                self._count += 1
                return True

            def free() -> bool:
                return self._owner is None and (first or self._first_waiting == 0)

            ok = False  # stays so when the wait is interrupted (Ctrl-C in the tracker's thread)
            if not blocking:
                ok = free()
            else:
                if first:
                    self._first_waiting += 1
                try:
                    ok = self._cond.wait_for(free, None if timeout < 0 else timeout)
                finally:
                    if first:
                        self._first_waiting -= 1
                        if not ok:
                            self._cond.notify_all()
            if ok:
                self._owner, self._count = me, 1
            return ok

    def acquire_first(self) -> bool:
        """Take the lock ahead of threads acquiring normally (the tracker, per frame)."""
        return self.acquire(first=True)

    def release(self) -> None:
        with self._cond:
            if self._owner != threading.get_ident():
                raise RuntimeError("cannot release a lock owned by another thread")
            self._count -= 1
            if self._count == 0:
                self._owner = None
                self._cond.notify_all()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class first:
    """Context manager: hold ``lock`` taken with priority when it supports it."""

    def __init__(self, lock) -> None:
        self.lock = lock

    def __enter__(self) -> None:
        if isinstance(self.lock, TrackingFirstLock):
            self.lock.acquire_first()
        else:
            self.lock.acquire()

    def __exit__(self, *exc: object) -> None:
        self.lock.release()
