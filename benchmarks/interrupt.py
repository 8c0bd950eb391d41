"""Ctrl-C at fixed moments of `occvo run`: each must end with exit 130 and one line on stderr besides the progress.

python benchmarks/interrupt.py [--at 2 5 10 15 20] [-- run options, default: the synthetic scene]
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def progress(line: str) -> bool:
    """The progress a run writes to stderr: the kernels' loading line and the frame bar."""
    return line.startswith("occvo run: loading") or line.startswith("OCC-VO ") or not line.strip()


def interrupt_at(seconds: float, run_args: list[str]) -> dict:
    out = Path(tempfile.mkdtemp(prefix="occvo-interrupt-"))
    try:
        cmd = [str(Path(sys.executable).with_name("occvo")), "run", "--out", str(out / "run"), *run_args]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(seconds)
        sent = proc.poll() is None
        if sent:
            proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate()
        lines = [s for s in stderr.replace("\r", "\n").splitlines() if not progress(s)]
        partial = [p.name for p in (out / "run").rglob("*")] if (out / "run").exists() else []
        return {"at_s": seconds, "sent": sent, "exit": proc.returncode, "lines": lines, "files": partial}
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--at", type=float, nargs="+", default=[2, 5, 10, 15, 20], help="seconds after the start")
    parser.add_argument("run_args", nargs="*", help="options of occvo run (after --)")
    args = parser.parse_args()
    ok = True
    for at in args.at:
        r = interrupt_at(at, args.run_args)
        # a signal that reaches the run as it exits, its work done and written, leaves exit 0 and no line
        done = r["exit"] == 0 and not r["lines"] and len(r["files"]) == 7
        good = not r["sent"] or done or (r["exit"] == 130 and r["lines"] == ["occvo run: interrupted"])
        ok &= good
        what = "interrupted" if r["sent"] and r["exit"] != 0 else "had ended" if not r["sent"] else "ended as it came"
        print(
            f"{at:5.1f} s: {what}, exit {r['exit']}, stderr {r['lines']}, files {r['files']} {'ok' if good else 'BAD'}"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
