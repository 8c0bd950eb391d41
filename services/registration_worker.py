"""`python -m occvo_services.registration_worker`: the registration worker (services/registration/: one session a
stream, its phases, scheduling, paging, map output, snapshots and resume; wired to Zenoh in worker.py)."""

from __future__ import annotations

import sys

from occvo_services.registration.session import StreamSession
from occvo_services.registration.worker import RegistrationWorker, main

__all__ = ["RegistrationWorker", "StreamSession", "main"]

if __name__ == "__main__":
    sys.exit(main())
