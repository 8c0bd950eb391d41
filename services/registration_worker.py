"""`python -m occvo_services.registration_worker`: the registration worker (services/registration/: the stream lane,
durability, paging, map publishing and queries, wired to Zenoh in worker.py)."""

from __future__ import annotations

import sys

from occvo_services.registration.state import StreamState
from occvo_services.registration.worker import RegistrationWorker, main

__all__ = ["RegistrationWorker", "StreamState", "main"]

if __name__ == "__main__":
    sys.exit(main())
