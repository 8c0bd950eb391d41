"""SIGINT and SIGTERM as a threading.Event, set outside the signal handler.

A Python handler runs in the main thread between two of its bytecodes. When the main thread is inside that very
Event's wait() (every service's main loop is `while not event.wait(0.2)`), it may hold the lock that Event.set()
takes, and set() called from the handler then waits for it forever: a Ctrl-C or SIGTERM that never stops the
process. So the handler only writes a byte to a pipe, and a thread of its own reads it and sets the event."""

from __future__ import annotations

import contextlib
import os
import signal
import threading


def set_on_signal(event: threading.Event, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
    """event.set() soon after any of `signals` arrives (call from the main thread, as signal.signal asks)."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)  # a handler never blocks

    def relay() -> None:
        while os.read(read_fd, 1):
            event.set()

    def note(*_) -> None:
        with contextlib.suppress(BlockingIOError):  # a full pipe already holds wake-ups enough for the relay
            os.write(write_fd, b"\0")

    threading.Thread(target=relay, name="signals", daemon=True).start()
    for sig in signals:
        signal.signal(sig, note)
