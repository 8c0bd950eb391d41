"""run.json: what made an output folder (occvo's version, the command, its options and the effective configuration),
so a run can be told apart from another and repeated."""

from __future__ import annotations

import json
import platform
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path

from occvo_cli import __version__


def write_run_record(out: str | Path, args, config) -> Path:
    from occvo_services.store_url import redact  # no password in a record, whatever option carried one

    options = {k: v for k, v in vars(args).items() if k not in ("func", "debug", "argv")}
    record = {
        "occvo_version": __version__,
        "command": redact(shlex.join(["occvo", *getattr(args, "argv", sys.argv[1:])])),
        "options": json.loads(redact(json.dumps(options, default=str))),
        "config": config.model_dump(mode="json"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    path = Path(out) / "run.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path
