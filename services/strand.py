"""A strand: one owner's tasks run in the order given, one at a time, on the threads of a pool the worker shares among
all its streams (no thread of the owner's own). A stream's lane, its work after its poses and its map updates are
each a strand: the threads stay as many as the pools hold, whatever the number of streams."""

from __future__ import annotations

import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor


def pool(threads: int, name: str, initializer=None) -> ThreadPoolExecutor:
    """A worker-wide pool of `threads` threads, all started now by the calling thread: a thread starts at the
    niceness of the one that made it, and a pool started lazily would take that of whichever thread gave it work."""
    executor = ThreadPoolExecutor(threads, name, initializer=initializer)
    all_started = threading.Barrier(threads)  # each task holds its thread until every thread exists
    for _ in range(threads):
        executor.submit(all_started.wait, 60.0)
    return executor


class Strand:
    """Tasks of one owner, in order and never two at once; between two tasks the strand goes to the back of the pool's
    queue, so the pool's threads take the strands in turn."""

    def __init__(self, executor: ThreadPoolExecutor):
        self._executor = executor
        self._cond = threading.Condition()
        self._tasks: deque = deque()
        self._scheduled = False  # a step of this strand is queued in the pool or running
        self.native_id: int | None = None  # the thread running (or that last ran) its task

    def submit(self, fn, *args) -> Future:
        """fn(*args) after every task submitted before it; its Future."""
        future: Future = Future()
        with self._cond:
            self._tasks.append((future, fn, args))
            if self._scheduled:
                return future
            self._scheduled = True
        self._schedule()
        return future

    def _schedule(self) -> None:
        try:
            self._executor.submit(self._step)
        except RuntimeError:  # the pool was shut down (the worker stops): the strand's tasks left run here, in order
            more = True
            while more:
                more = self._run_one()

    def _step(self) -> None:
        if self._run_one():
            self._schedule()

    def _run_one(self) -> bool:
        """The next task; True if more wait."""
        with self._cond:
            future, fn, args = self._tasks.popleft()
        self.native_id = threading.get_native_id()
        if future.set_running_or_notify_cancel():
            try:
                future.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - the task's error is its Future's
                future.set_exception(exc)
        with self._cond:
            if self._tasks:
                return True
            self._scheduled = False
            self._cond.notify_all()
            return False

    @property
    def idle(self) -> bool:
        """No task queued or running."""
        with self._cond:
            return not self._scheduled

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Until no task is queued or running; False if that did not happen within timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._scheduled, timeout)
