"""The registration worker's store faults without a service: the order frames refused or turned away are waited for
in (services/registration/store_faults.py), and the outage's probe."""

from __future__ import annotations

import logging
import threading
from types import SimpleNamespace

from occvo_services.registration.store_faults import Refusals, StoreOutage
from occvo_services.store.errors import StoreUnavailable
from occvo_services.telemetry import Stats


def _session():
    reports = []
    return SimpleNamespace(refusals=Refusals(lambda code, message, seq: reports.append((code, seq))), reports=reports)


def _waits(s, seq: int) -> bool:
    return s.refusals.waits(seq)


def refused(s, k: int) -> None:
    s.refusals.refused(k)


def test_frames_turned_away_come_back_in_order():
    """k refused; k+1 and k+2 turned away; k comes: registered; then k+2 before k+1 waits (a jump it would be)."""
    s = _session()
    refused(s, 5)
    assert _waits(s, 6) and _waits(s, 7)
    assert not _waits(s, 5)  # the refused frame, sent again
    assert _waits(s, 7)  # k+1 first: k+2 now would be held as a jump and k+1 lost once k+3 confirmed it
    assert not _waits(s, 6) and not _waits(s, 7) and not _waits(s, 8)
    assert not _waits(s, 3)  # an older frame (a resend) is never held back
    assert s.reports == [("not_stored", 6), ("not_stored", 7), ("not_stored", 7)]


def test_a_new_trajectory_forgets_the_refusals():
    s = _session()
    refused(s, 9)
    assert _waits(s, 10) and not _waits(s, 0) and not _waits(s, 1)


def test_the_outage_ends_when_the_store_answers_or_the_worker_stops():
    answers = [StoreUnavailable("away"), StoreUnavailable("away"), None]

    def ping():
        if (a := answers.pop(0)) is not None:
            raise a

    stopping, log = threading.Event(), logging.getLogger("test")
    outage = StoreOutage(SimpleNamespace(ping=ping), stopping, Stats(), log)
    assert not outage.saw(RuntimeError("disk full")) and not outage.down
    assert outage.saw(StoreUnavailable("store x unreachable")) and outage.down and "unreachable" in outage.why
    assert outage.wait_back() and not outage.down and answers == []
    outage.saw(StoreUnavailable("again"))
    answers[:] = [StoreUnavailable("away")] * 100
    stopping.set()
    assert not outage.wait_back() and outage.down
