"""Where the tasks of a sweep (and of ``vocab train``'s descriptor extraction) run: on Ray.

:class:`Engine` runs a picklable function over a list of items. With Ray installed (the
optional extra ``cluster``: ``pip install 'orbslam_hgcn[cluster]'``) it starts a local Ray
instance with ``jobs`` CPUs, or joins the cluster at ``address``, and keeps at most ``jobs``
tasks in flight; Ray schedules them, ships their arguments and results, and retries a task
once when the worker process running it dies (``max_retries``). Without Ray, or with
``use_ray=False``, the items run one after the other in this process, with the same
results. On a cluster the paths given to the tasks (datasets, output folders) must be
visible to every node (a shared file system), and the package installed there.
"""

from __future__ import annotations

import importlib.util
import logging
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from orbslam_hgcn.errors import ConfigError

log = logging.getLogger(__name__)

INSTALL_HINT = "install the optional extra: pip install 'orbslam_hgcn[cluster]' (Ray)"


def ray_available() -> bool:
    """Whether Ray can be imported."""
    return importlib.util.find_spec("ray") is not None


class TaskFailed(Exception):
    """A task that Ray could not run to its end (its worker died twice, or it raised)."""


class Engine:
    """Runs tasks on Ray (local instance or a cluster) or, without Ray, in order here.

    Use as a context manager: a Ray instance started on entry is shut down on exit; one
    already initialised in this process (``ray.init`` by the caller) is used and left running.
    use_ray: None uses Ray when it is installed; False never; True requires it.
    """

    def __init__(self, jobs: int = 1, address: str | None = None, use_ray: bool | None = None,
                 max_retries: int = 1) -> None:
        if jobs < 1:
            raise ConfigError(f"--jobs must be at least 1, found {jobs}")
        available = ray_available()
        if (use_ray or address) and not available:
            raise ConfigError(f"{'--address' if address else 'Ray'}: Ray is not installed; {INSTALL_HINT}")
        if address and use_ray is False:
            raise ConfigError("--address needs Ray; it cannot be combined with running without Ray")
        self.jobs = jobs
        self.address = address
        self.use_ray = available if use_ray is None else use_ray
        self.max_retries = max_retries
        self._own = False
        self._ray: Any = None
        if not self.use_ray and jobs > 1:
            log.warning("Ray is not installed: the %d-way --jobs runs in order instead; %s", jobs, INSTALL_HINT)

    @property
    def name(self) -> str:
        if not self.use_ray:
            return "in order (no Ray)"
        return f"Ray at {self.address}" if self.address else f"local Ray, {self.jobs} job(s)"

    def __enter__(self) -> Engine:
        if self.use_ray:
            import ray

            if not ray.is_initialized():
                if self.address:
                    ray.init(address=self.address, logging_level=logging.WARNING, log_to_driver=False)
                else:
                    ray.init(num_cpus=self.jobs, include_dashboard=False, logging_level=logging.WARNING,
                             log_to_driver=False)
                self._own = True
            self._ray = ray
        return self

    def __exit__(self, *exc: object) -> None:
        if self._ray is not None and self._own:
            self._ray.shutdown()
        self._ray, self._own = None, False

    def imap_unordered(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        """(index, fn(item)) for every item, as each finishes. A task that Ray could not run
        to its end yields a :class:`TaskFailed` as its result. Stopping the iteration
        (Ctrl-C in the caller) cancels the tasks still in flight."""
        if self._ray is None:
            if self.use_ray:
                raise RuntimeError("Engine used outside its 'with' block")
            for i, item in enumerate(items):
                yield i, fn(item)
            return
        ray = self._ray
        remote = ray.remote(num_cpus=1, max_retries=self.max_retries)(fn)
        pending: dict[Any, int] = {}
        nxt = 0
        try:
            while nxt < len(items) or pending:
                while nxt < len(items) and len(pending) < self.jobs:
                    pending[remote.remote(items[nxt])] = nxt
                    nxt += 1
                ready, _ = ray.wait(list(pending), num_returns=1)
                i = pending.pop(ready[0])
                try:
                    result = ray.get(ready[0])
                except (ray.exceptions.RayTaskError, ray.exceptions.RayError) as exc:
                    lines = str(exc).strip().splitlines()
                    result = TaskFailed(lines[-1] if lines else type(exc).__name__)
                yield i, result
        finally:
            for ref in pending:
                ray.cancel(ref)
