"""Faults to inject into a run (tests/test_faults.py): an extraction process that raises or
dies at a given request. The class is built inside the child process, which imports it
from here (tests/ is on the path the child inherits)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

from orbslam_hgcn.childprocess import ChildProcess
from orbslam_hgcn.runtime.extraction import ExtractionError, ExtractionProcess, Extractors


class FailingExtractors(Extractors):
    """The extraction process's object, failing at its ``fail_at``-th extraction: raising
    an error (``die`` False) or killing its own process (``die`` True). It fails once per
    ``once`` file: the process that fails creates it, and a process started after it finds
    it and extracts normally."""

    def __init__(self, configs, camera, fail_at: int, die: bool, once: str) -> None:
        super().__init__(configs, camera)
        self.fail_at, self.die, self.once, self.calls = fail_at, die, Path(once), 0

    def extract(self, name, image):
        self.calls += 1
        if self.calls == self.fail_at and not self.once.exists():
            self.once.touch()
            if self.die:
                os.kill(os.getpid(), signal.SIGKILL)
            raise RuntimeError(f"injected extraction failure at request {self.calls}")
        return super().extract(name, image)


def failing_extraction(fail_at: int, die: bool, once: Path) -> type[ExtractionProcess]:
    """An ExtractionProcess class whose child serves :class:`FailingExtractors`."""

    class _Failing(ExtractionProcess):
        def __init__(self, configs, camera, nice: int = 0) -> None:
            self._child = ChildProcess(
                "extraction", FailingExtractors, (dict(configs), camera, fail_at, die, str(once)), ExtractionError,
                nice=nice,
            )

        def start(self) -> None:
            # Waits for the child (a run does not): every frame's extraction is then a
            # request to it, and request fail_at is frame fail_at's.
            super().start()
            self._child.call("ping")

    return _Failing


class SlowExtractors(Extractors):
    """The extraction process's object, built ``delay_s`` late (a child that starts slowly:
    a loaded machine, a cold disk)."""

    def __init__(self, configs, camera, delay_s: float) -> None:
        import time

        time.sleep(delay_s)
        super().__init__(configs, camera)


def extraction_process(delay_s: float, wait: bool, made: list) -> type[ExtractionProcess]:
    """An ExtractionProcess class whose child builds its extractors ``delay_s`` late; with
    ``wait`` its start() waits for the child (a run's does not). Each instance is appended
    to ``made``."""

    class _Slow(ExtractionProcess):
        def __init__(self, configs, camera, nice: int = 0) -> None:
            self._child = ChildProcess("extraction", SlowExtractors, (dict(configs), camera, delay_s), ExtractionError,
                                       nice=nice)  # fmt: skip
            made.append(self)

        def start(self) -> None:
            super().start()
            if wait:
                self._child.call("ping")

    return _Slow
