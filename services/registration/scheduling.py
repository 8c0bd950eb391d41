"""Who runs what, at which priority, in the registration worker.

- The kernel team (`Scheduler.kernels`): the one thread of the process whose numba kernels may use several cores
  (occvo_core.registration.kernels.own_team). A session hands it its frame's registration when its OccVO may use
  more than one thread and no other call holds the team (else it runs in the lane's thread on one: no stream's frame
  queues behind another's); caught up, the frame's commit and pose publication follow in the same call. Once the kernels
  are done, the team's OpenMP threads (spinning after a kernel) are lowered (IdleTeam) and raised before the next.
- The after-pose pool (AFTER_POSE_THREADS, after_pose_nice below the lanes), where a session's strand
  (`StreamThreads.after`, services/strand.py) runs its frames' work after their poses in order (loop closure, the map
  update, the second store write). When a lane waits for that work, the thread running it is raised to the lane's
  priority until it ends (priority inheritance: `StreamThreads.wait_after_pose`).
- The map pool (MAP_THREADS), where a session's strand (`StreamThreads.map`) cuts and sends its tiles in frame order,
  at the lanes' priority (it holds the GIL).
- Kernel threads of a frame (`Scheduler.fair_threads`): the cores other processes leave free, shared among the
  lanes registering now."""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import Future, wait

from occvo_core.free_cores import FREE_CORES
from occvo_core.registration.kernels import own_team, use_threads
from occvo_services.os_tuning import (
    IdleTeam,
    hold_priority,
    lower_priority,
    name_os_thread,
    release_priority,
    run_delay_ms,
)
from occvo_services.strand import Strand, pool
from occvo_services.telemetry import log_event

CORES = len(FREE_CORES.cpus)  # the cores this process may run on
AFTER_POSE_THREADS = 4  # the streams' work after their poses, this many at once
MAP_THREADS = 2  # the streams' map updates (they hold the GIL: more would only wait for it)


def _map_thread_start() -> None:
    """The map thread keeps the lane's priority; its kernels run on one thread."""
    name_os_thread()
    use_threads(1)


class Scheduler:
    """The worker-wide part: the kernel team, background threads' niceness, and the one warning when a waited-for
    thread cannot be raised."""

    def __init__(self, after_pose_nice: int, stats, log):
        self.after_pose_nice, self.stats, self.log = after_pose_nice, stats, log
        self._team = pool(1, "kernels", initializer=name_os_thread)
        self._team_lock = threading.Lock()
        self._team_busy = False  # a call holds the kernel team (Scheduler.kernels)
        self._team_ident = self._team.submit(threading.get_ident).result()
        self.after_pool = pool(AFTER_POSE_THREADS, "after-pose", initializer=self.background_thread)
        self.map_pool = pool(MAP_THREADS, "map", initializer=_map_thread_start)
        self._idle_team = IdleTeam()
        self._boost_refused = False
        if not self._team.submit(own_team).result():
            log_event(log, "another thread of this process runs kernels on several cores: lanes run on one")

    def kernels(self, vo, fn, *args) -> tuple[object, float]:
        """(fn(*args), ms the team thread waited for a core): in the kernel team when vo may use several kernel
        threads and the team is free, else in the calling thread on one: a frame never waits in the team's queue for
        another stream's whole registration or map update (a stream of heavy frames holds the team several times
        longer than a normal frame)."""
        if vo.threads == 1 or not self._take_team():
            return fn(*args), 0.0

        def call():
            w0 = run_delay_ms()
            self._idle_team.restore()  # kernels follow: the team's threads back to the lanes' priority
            result = fn(*args)
            return result, run_delay_ms() - w0

        try:
            return self._team.submit(call).result()
        finally:
            with self._team_lock:
                self._team_busy = False

    def _take_team(self) -> bool:
        """The kernel team for the caller's call, if no other call holds it."""
        with self._team_lock:
            if self._team_busy:
                self.stats.inc("kernels_beside_team")
                return False
            self._team_busy = True
            return True

    def kernels_done(self, threads: int) -> None:
        """After a caught-up frame's kernels: in the team thread, its spinning OpenMP threads make way for the pose
        (a frame that ran beside the held team, in its lane, has none)."""
        if threads > 1 and threading.get_ident() == self._team_ident:
            self._idle_team.lower(threads)

    @staticmethod
    def fair_threads(busy_lanes: int) -> int:
        """Kernel threads for a frame about to be registered: the cores other processes (other shards among them)
        leave free, divided among this worker's lanes busy now (this one included), so one stream alone uses every
        free core and several streams do not oversubscribe them."""
        return max(1, FREE_CORES.threads(CORES) // max(1, busy_lanes))

    def background_thread(self) -> None:
        """Start of a thread doing work off the poses' path: after_pose_nice below the lanes; its own kernels run on
        one thread (a session's OccVO.complete goes to the kernel team)."""
        name_os_thread()
        use_threads(1)
        if not lower_priority(self.after_pose_nice):
            log_event(
                self.log,
                "cannot lower a background thread's priority here; it runs at the lanes'",
                logging.WARNING,
                thread=threading.current_thread().name,
            )

    def boost_refused(self) -> None:
        if not self._boost_refused:
            self._boost_refused = True
            log_event(
                self.log,
                "cannot raise a waited-for after-pose thread to the lanes' priority (needs "
                "CAP_SYS_NICE or RLIMIT_NICE, e.g. LimitNICE=+0): it finishes niced",
                logging.WARNING,
            )

    def shutdown(self) -> None:
        self._team.shutdown(wait=False)  # idle unless a lane's frame did not finish in time

    def close_pools(self) -> None:
        """After the sessions' last work: a strand's task left then runs in the thread that gives it."""
        self.after_pool.shutdown(wait=False)
        self.map_pool.shutdown(wait=False)


class CatchUp:
    """Sessions catching up (reopened from the store: moved from a lost worker, or back from idle) register before
    the other lanes' next frames: their clients waited longest, and on a saturated worker a fair share would stretch
    a failover over every other lane's frames. A lane waits at most max_wait_s, so a long replay stalls no one."""

    def __init__(self, max_wait_s: float = 2.0):
        self.max_wait_s = max_wait_s
        self._cond = threading.Condition()
        self._active: set[str] = set()

    def begin(self, stream: str) -> None:
        with self._cond:
            self._active.add(stream)

    def end(self, stream: str) -> None:
        with self._cond:
            self._active.discard(stream)
            if not self._active:
                self._cond.notify_all()

    def wait_turn(self, stream: str) -> None:
        """Before a frame's registration: wait while other sessions catch up."""
        with self._cond:
            if self._active and stream not in self._active:
                self._cond.wait_for(lambda: not self._active, self.max_wait_s)


class StreamThreads:
    """A session's after-pose strand and map strand on the worker's pools, and priority inheritance for the thread
    running its after-pose work."""

    def __init__(self, stream: str, scheduler: Scheduler):
        self.stream, self.scheduler = stream, scheduler
        self.after: Strand | None = None
        self.tail: Future | None = None  # the last job in the after-pose strand
        self.map: Strand | None = None
        self.map_tail: Future | None = None  # the last frame's tiles
        # set: the after-pose work may start (a frame came in, or the pose had its head start)
        self.head_start = threading.Event()
        self.head_start.set()
        self._lock = threading.Lock()  # orders a lane's boost against the end of the work it boosts
        self._running = False  # a frame's work after its pose is due or running
        self._tid: int | None = None  # native id of the thread running its after-pose work now
        self._wanted: int | None = None  # the niceness of a lane waiting for that work
        self.boosted = False  # that thread runs at the lane's priority (the lane waits for it)

    def start(self) -> None:
        if self.after is None:
            self.after = Strand(self.scheduler.after_pool)
        if self.map is None:
            self.map = Strand(self.scheduler.map_pool)
            self.map_tail = self.map.submit(int)

    def work_due(self) -> None:
        """A frame was registered: its work after the pose is due (a lane waiting for it now raises the thread)."""
        self._running = True

    def submit_after(self, fn, *args, head_start_s: float | None = None) -> Future:
        """fn(*args) in the after-pose strand, after the jobs before it. head_start_s: it waits that long or until
        the stream's next frame comes."""
        if head_start_s is not None:
            self.head_start.clear()
        self.tail = self.after.submit(self._run, fn, args, head_start_s)
        return self.tail

    def _run(self, fn, args, head_start_s: float | None) -> None:
        if head_start_s is not None:
            self.head_start.wait(head_start_s)
        with self._lock:  # a pool's thread: a lane that waited before the work began raises it now
            self._tid = threading.get_native_id()
            self._raise()
        try:
            fn(*args)
        finally:
            with self._lock:
                self._running = False
                if self.boosted:  # niced again for the next stream's work
                    release_priority(self._tid)
                    self.boosted = False
                self._tid = self._wanted = None

    def wait_after_pose(self) -> None:
        """The lane waits for the last frame's work after its pose: that work now holds up a pose, so it runs at the
        lane's priority until it ends (without it a niced loop closure waited behind every other stream's lane).
        Raising a thread needs CAP_SYS_NICE or an RLIMIT_NICE that allows it; without either it finishes niced."""
        if self.tail is None:
            return
        if not self.tail.done():
            self._boost()
        self.tail.result()

    def _boost(self) -> None:
        with self._lock:
            if not self._running or self.boosted:
                return
            self._wanted = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
            self._raise()

    def _raise(self) -> None:
        """Under _lock: the thread running the work to the waiting lane's niceness."""
        if self._wanted is None or self._tid is None or self.boosted:
            return
        if hold_priority(self._tid, self._wanted):
            self.boosted = True
            self.scheduler.stats.inc("after_pose_boosted")
        else:
            self.scheduler.boost_refused()

    def submit_map(self, fn, *args) -> None:
        """fn(*args) in the map strand once the last frame's tiles are out (one frame's tiles at most wait there)."""
        self.wait_map()
        self.map_tail = self.map.submit(fn, *args)

    def wait_map(self) -> None:
        if self.map_tail is not None:
            self.map_tail.result()

    def settle(self) -> None:
        """The jobs handed to the threads so far done (head starts kept)."""
        wait([f for f in (self.tail, self.map_tail) if f is not None])

    def drain(self) -> None:
        """Every job handed to the threads done (head starts end now)."""
        self.head_start.set()
        if self.tail is not None:
            self.tail.result()
        self.wait_map()

    def close(self) -> None:
        """The strands end (after their jobs)."""
        self.drain()
        self.after = self.tail = self.map = self.map_tail = None
