"""run.json: what made an output folder (occvo's version and git commit, the command, its options, the effective
configuration, a digest of the input and the versions of the libraries that decide the numbers), so a run can be told
apart from another and repeated."""

from __future__ import annotations

import hashlib
import json
import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from occvo_cli import __version__

SOURCE_ROOT = Path(__file__).resolve().parents[1]  # the checkout's root when occvo runs from one
LIBRARIES = {"numpy": "numpy", "numba": "numba", "torch": "torch", "zenoh": "eclipse-zenoh"}  # name: distribution


def write_run_record(out: str | Path, args, config, source=None) -> Path:
    from occvo_services.store.url import redact  # no password in a record, whatever option carried one

    options = {k: v for k, v in vars(args).items() if k not in ("func", "debug", "argv")}
    record = {
        "occvo_version": __version__,
        **git_commit(),
        "command": redact(shlex.join(["occvo", *getattr(args, "argv", sys.argv[1:])])),
        "options": json.loads(redact(json.dumps(options, default=str))),
        "config": config.model_dump(mode="json"),
        "input_digest": input_digest(args, source) if source is not None else None,
        "libraries": library_versions(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    path = Path(out) / "run.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def git_commit(root: Path = SOURCE_ROOT) -> dict:
    """git_commit: the commit of the checkout occvo runs from, git_dirty: whether its tracked files differ from it;
    both None for an installed copy (a folder that is not a checkout's root: a wheel inside another project's tree
    is not that project's commit) or where git is missing."""
    none = {"git_commit": None, "git_dirty": None}
    try:
        top = _git(root, "rev-parse", "--show-toplevel")
        if top is None or Path(top).resolve() != Path(root).resolve():
            return none
        changes = _git(root, "status", "--porcelain", "--untracked-files=no")
        return {"git_commit": _git(root, "rev-parse", "HEAD"), "git_dirty": bool(changes)}
    except OSError:  # no git on the machine
        return none


def _git(root: Path, *argv: str) -> str | None:
    proc = subprocess.run(["git", "-C", str(root), *argv], capture_output=True, text=True, timeout=10, check=False)
    return proc.stdout.strip() if proc.returncode == 0 else None


def input_digest(args, source) -> dict:
    """sha256 over the input frames' files in frame order (content only: a moved or renamed scene keeps its digest),
    or over the synthetic scene's parameters."""
    if args.input is not None:
        files = getattr(source, "files", None)
        if files is None:  # a reader that keeps no frame files: no digest rather than a wrong one
            return {"sha256": None, "over": "no frame files", "frames": len(source)}
        digest = hashlib.sha256()
        for path in files[: len(source)]:  # --frames N: the frames run
            digest.update(hashlib.sha256(Path(path).read_bytes()).digest())
        return {"sha256": digest.hexdigest(), "over": "frame files", "frames": len(source)}
    parameters = {"seed": args.seed, "frames": len(source), "rate_hz": args.rate, "noise": args.noise}
    text = json.dumps(parameters, sort_keys=True).encode()
    return {"sha256": hashlib.sha256(text).hexdigest(), "over": "synthetic scene parameters", **parameters}


def library_versions() -> dict:
    found = {}
    for name, dist in LIBRARIES.items():
        try:
            found[name] = version(dist)
        except PackageNotFoundError:
            found[name] = None
    return found
