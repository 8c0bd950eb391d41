"""A stop signal that lands while the main thread holds its event's lock (as Event.wait() does around its wait, in
every service's main loop) must still stop the process: set() called in the handler waited for that lock forever."""

import subprocess
import sys
import textwrap

CHILD = textwrap.dedent(
    """
    import os, signal, threading
    {setup}
    with event._cond:  # the lock Event.wait() holds on entry and on waking: the handler runs in here
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):
            pass
    print("stopped" if event.wait(10) else "still running", flush=True)
    """
)
OLD = "event = threading.Event()\nsignal.signal(signal.SIGTERM, lambda *_: event.set())"
NEW = (
    "from occvo_services.stop_signals import set_on_signal\n"
    "event = threading.Event()\nset_on_signal(event, (signal.SIGTERM,))"
)


def _run(setup: str, timeout: float = 30) -> subprocess.CompletedProcess | None:
    try:
        return subprocess.run(
            [sys.executable, "-c", CHILD.format(setup=setup)], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return None


def test_a_signal_in_the_events_lock_window_stops_the_process():
    done = _run(NEW)
    assert done is not None, "the process hung on its own stop signal"
    assert done.stdout.strip() == "stopped", done.stderr


def test_the_handler_that_sets_the_event_itself_hangs_there():
    """The window is real: the old handler, Event.set() in the handler, never returns (the child is killed)."""
    assert _run(OLD, timeout=8) is None
