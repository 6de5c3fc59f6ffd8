"""The generic stage worker: order, draining, error propagation, clean shutdown."""

import os
import sys
import threading

import pytest

from orbslam_hgcn.runtime.worker import Worker, WorkerError


def test_items_processed_in_order_and_drained_on_stop():
    seen = []
    w = Worker("t", seen.append).start()
    for i in range(100):
        w.submit(i)
    w.stop()
    assert seen == list(range(100))
    assert not any(t.name == "orbslam-t" and t.is_alive() for t in threading.enumerate())


def test_stage_exception_reaches_the_caller():
    def handler(item):
        if item == 3:
            raise ValueError("bad keyframe")

    w = Worker("failing", handler).start()
    for i in range(3):
        w.submit(i)
    w.submit(3)
    with pytest.raises(WorkerError, match="bad keyframe") as info:
        w.wait_idle()
        w.submit(4)
    assert isinstance(info.value.__cause__, ValueError)
    with pytest.raises(WorkerError):
        w.stop()


def test_stop_without_drain_discards_waiting_items():
    gate = threading.Event()
    seen = []

    def handler(item):
        gate.wait()
        seen.append(item)

    w = Worker("slow", handler).start()
    for i in range(10):
        w.submit(i)
    stopper = threading.Thread(target=w.stop, kwargs={"drain": False})
    stopper.start()
    gate.set()
    stopper.join(5)
    assert not stopper.is_alive()
    assert len(seen) < 10


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="threads have their own niceness on Linux")
def test_worker_thread_runs_at_lower_priority():
    def niceness() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    base = niceness()
    seen = []
    w = Worker("nice", lambda _: seen.append(niceness()), nice=3).start()
    w.submit(0)
    w.stop()
    assert seen == [min(base + 3, 19)]
    assert niceness() == base  # the caller's thread keeps its priority
