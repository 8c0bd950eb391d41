"""OS tuning of a worker's threads and heap: niceness (lower, hold and release), OS thread names, glibc's malloc
thresholds and heap trim. Each call returns False (or does nothing) where the OS does not allow it; the work is the
same, only its scheduling or memory differs."""

from __future__ import annotations

import ctypes
import os
import sys
import threading


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL(None)  # the process's own symbols: libc's prctl and setpriority, loaded once
    except OSError:
        return None


_LIBC = _libc()


def lower_priority(nice: int) -> bool:
    """Run the calling thread `nice` steps below the thread that made it (Linux threads are tasks with their own
    niceness; raising it needs no privilege). False where that is not possible: the thread keeps its priority."""
    if nice <= 0:
        return True
    try:
        tid = threading.get_native_id()
        return set_thread_nice(tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (OSError, AttributeError):
        return False


def name_os_thread(name: str | None = None) -> None:
    """Name the calling OS thread (first 15 bytes; default: its Python name), so `top -H`, `ps -L` and
    /proc/<pid>/task/*/comm tell the lanes and background threads apart (Python < 3.14 leaves them all "python")."""
    try:
        _LIBC.prctl(15, (name or threading.current_thread().name).encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except AttributeError:  # no libc handle or no prctl (not Linux): the thread works the same, unnamed
        return


def set_thread_nice(tid: int, nice: int) -> bool:
    """Set a thread's niceness; False where not allowed (raising priority needs CAP_SYS_NICE or RLIMIT_NICE).
    Through libc, which ctypes calls with the GIL released: a thread that lowers itself is often preempted inside
    the call, and os.setpriority holds the GIL across it (in a worker's profile a fifth of the time the GIL was
    held, every other thread waiting for the niced one to get a core back)."""
    if hasattr(_LIBC, "setpriority"):
        return _LIBC.setpriority(os.PRIO_PROCESS, tid, nice) == 0
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (OSError, AttributeError):
        return False
    return True


_held_lock = threading.Lock()
_held: dict[int, tuple[int, int]] = {}  # tid -> (holds, its niceness once none is left)


def hold_priority(tid: int, nice: int) -> bool:
    """Keep thread `tid` at niceness `nice` or better until release_priority(tid). Holds nest: a niced after-pose
    thread its waiting lane raised (priority inheritance) that also holds the store's write lock (a priority ceiling)
    goes back to its niceness when both are over. True if the thread runs at `nice` or better now; False where
    raising it is not allowed (CAP_SYS_NICE or RLIMIT_NICE)."""
    with _held_lock:
        if tid in _held:
            count, rest = _held[tid]
            _held[tid] = (count + 1, rest)
            return True
        try:
            rest = os.getpriority(os.PRIO_PROCESS, tid)
        except (OSError, AttributeError):
            return False
        if rest <= nice:
            return True  # nothing to raise (and nothing for release_priority to undo)
        if not set_thread_nice(tid, nice):
            return False
        _held[tid] = (1, rest)
        return True


def release_priority(tid: int) -> None:
    """End one hold_priority(tid) that returned True; the last one puts the thread back to its niceness."""
    with _held_lock:
        if tid not in _held:
            return
        count, rest = _held[tid]
        if count > 1:
            _held[tid] = (count - 1, rest)
        else:
            del _held[tid]
            set_thread_nice(tid, rest)


def large_blocks_from_mmap(threshold: int = 16 << 20, trim: int = 64 << 20) -> bool:
    """Fix glibc's mmap threshold and heap trim threshold (False where malloc is not glibc's). By default the mmap
    threshold rises to the largest block freed, up to 32 MB: then even the map's big arrays come from the heap, which
    fragments, and a worker's RSS creeps up over hours of a long drive. Fixed, blocks over `threshold` (map arrays, snapshot copies) are mmapped and returned when freed; a
    frame's temporaries (up to a few MB) come from a heap that keeps up to `trim` free at its top. A much lower
    threshold makes every temporary a fresh mapping faulted in page by page, and registration slower."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(-3, threshold)) and bool(libc.mallopt(-1, trim))  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False


def trim_heap() -> bool:
    """Give the heap's free pages back to the system now (glibc's malloc_trim; False elsewhere). Once, after start-up
    work whose temporaries are gone (the kernels' warm-up leaves tens of MB free but resident); not per frame: trimmed pages
    fault in again, and a periodic trim raised the eight-stream latency p99."""
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


GIL_SWITCH_S = 0.0005  # a worker's interpreter-lock turn (Python's default: 5 ms)


def short_gil_turns(interval_s: float = GIL_SWITCH_S) -> float:
    """Set the interpreter's switch interval for the whole process; returns the one before. A thread coming back
    from a compiled kernel (GIL released) waits for the lock until a thread running Python gives it up, which it
    is asked to after this interval; registration takes the lock back at every kernel, so beside any thread running
    Python (a stream's map tiles, a decode) a frame waited up to the interval that many times. scene-0101 offline
    beside one busy Python thread (benchmarks/gil_turns.py): step p50 670-682 ms at Python's 5 ms, 106-113 ms at
    0.5 ms, 26-28 ms alone; 0.1 ms gave 55-61 ms but can cost two Python threads 10-45% of their speed."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    return before


def few_malloc_arenas(arenas: int | None = None) -> bool:
    """Cap glibc's malloc arenas at `arenas` (default: one a core; False where malloc is not glibc's). glibc gives
    threads their own arenas, up to 8 a core, and a stream's lane and after-pose threads each take one: freed, their
    memory stayed in those arenas, malloc_trim or not (registration worker: 15 one-frame streams at once, retired,
    +70 MB, then +180 MB after a second 15; with two arenas 217 -> 225 MB both times). Threads beyond the cap share
    arenas; the GIL already serialises most of their allocations."""
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(-8, arenas or os.cpu_count() or 1))  # M_ARENA_MAX
    except (OSError, AttributeError):
        return False


def run_delay_ms() -> float:
    """Time the calling thread has spent runnable but waiting for a core, in ms since it started (the kernel's
    schedstat run_delay); 0.0 where not available. Differences of it tell a stage's wait for a core from its work."""
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/schedstat", "rb") as f:
            return int(f.read().split()[1]) / 1e6
    except (OSError, IndexError, ValueError):
        return 0.0


def may_raise_to(nice: int) -> bool:
    """Whether this process may set a thread's niceness back to `nice` once it is higher: CAP_SYS_NICE, or an
    RLIMIT_NICE that allows it (systemd's LimitNICE)."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NICE)[0]
        if soft == resource.RLIM_INFINITY or 20 - nice <= soft:
            return True
        with open("/proc/self/status") as f:
            caps = next(line for line in f if line.startswith("CapEff:"))
        return bool(int(caps.split()[1], 16) >> 23 & 1)  # CAP_SYS_NICE
    except (OSError, ImportError, AttributeError, StopIteration, ValueError):
        return False


class IdleTeam:
    """A kernel team's OpenMP threads spin on a core for about 7 ms after the team's last kernel (libgomp's default
    wait policy; sleeping at every barrier made each kernel wait for them to wake). Once a frame's kernels are done,
    lower() drops them to the lowest priority so that what its pose waits for next (the commit's fsync, the hops to
    the client) takes the core; restore() raises them again before the team's next kernels. Both are called from the
    team thread; its OpenMP threads are the threads of the process with its OS name (they inherit it). Inactive where
    the priority could not be raised back (no CAP_SYS_NICE or RLIMIT_NICE)."""

    def __init__(self):
        self.tids: list[int] = []
        self.scanned_for = 0  # the team size the threads were last looked up for
        self.nice: int | None = None  # the team thread's niceness, while its threads are lowered
        self.active: bool | None = None

    def lower(self, team_size: int) -> None:
        me = threading.get_native_id()
        nice = os.getpriority(os.PRIO_PROCESS, me)
        if self.active is None:
            self.active = may_raise_to(nice)
        if not self.active:
            return
        if team_size > self.scanned_for:  # a larger team than before has more threads
            self.tids, self.scanned_for = [t for t in _threads_named(_os_name(me)) if t != me], team_size
        self.nice = nice
        self.tids = [t for t in self.tids if set_thread_nice(t, 19)]  # a thread that ended is dropped

    def restore(self) -> None:
        if self.nice is not None:
            for t in self.tids:
                set_thread_nice(t, self.nice)
            self.nice = None


def _os_name(tid: int) -> str:
    with open(f"/proc/self/task/{tid}/comm") as f:
        return f.read().strip()


def _threads_named(name: str) -> list[int]:
    out = []
    for t in os.listdir("/proc/self/task"):
        try:
            if _os_name(int(t)) == name:
                out.append(int(t))
        except OSError:  # ended meanwhile
            continue
    return out
