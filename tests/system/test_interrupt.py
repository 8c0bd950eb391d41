"""Ctrl-C (SIGINT) at any moment of `occvo run` ends it with exit 130 and one line on stderr, and leaves nothing
half-written. The moments are found by what the run has printed, not by the clock: while the kernels load, after
the first frames (inside the numba kernels, where a KeyboardInterrupt surfaces as a SystemError), with a rerun
recording open."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
LOADING = re.compile(r"occvo run: loading[^\n]*\n")
FRAMES = re.compile(r"\|\s*([1-9]\d*)/\d+ \[")  # the frame bar with at least one frame done


def _interrupt_when(moment: re.Pattern, out: Path, *extra: str) -> tuple[int, str]:
    """Start a 100-frame synthetic run (far longer than reading its stderr takes), SIGINT it once its stderr
    matches moment; returns (exit code, stderr)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "run", "--frames", "100", "--out", str(out), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    seen = b""
    while not moment.search(seen.decode(errors="replace")):
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, f"the run ended before {moment.pattern!r}: {seen.decode(errors='replace')}"
        seen += chunk
    proc.send_signal(signal.SIGINT)
    stdout, rest = proc.communicate(timeout=600)
    assert stdout == b""
    return proc.returncode, (seen + rest).decode(errors="replace")


def _not_progress(err: str) -> list[str]:
    lines = err.replace("\r", "\n").splitlines()
    return [s for s in lines if s.strip() and not s.startswith(("occvo run: loading", "OCC-VO "))]


@pytest.mark.parametrize("moment", [LOADING, FRAMES], ids=["loading kernels", "registering frames"])
def test_ctrl_c_exits_130_with_one_line(moment, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").write_text("an earlier run's\n")
    code, err = _interrupt_when(moment, out)
    assert code == 130, err
    assert _not_progress(err) == ["occvo run: interrupted"], err
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]  # nothing written, nothing half-written
    assert (out / "summary.json").read_text() == "an earlier run's\n"


def test_ctrl_c_ends_another_commands_progress_bar_before_its_line(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "ablation", "--seeds", "0", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    seen = b""
    while b"ablation:" not in seen:  # the bar is up
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, seen.decode(errors="replace")
        seen += chunk
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=600)
    err = (seen + rest).decode(errors="replace")
    assert proc.returncode == 130, err
    assert err.endswith("\noccvo ablation: interrupted\n"), err  # on a line of its own, after the bar's


def test_ctrl_c_leaves_no_partial_recording(tmp_path):
    pytest.importorskip("rerun")
    code, err = _interrupt_when(FRAMES, tmp_path / "out", "--rerun", str(tmp_path / "run.rrd"))
    assert code == 130, err
    assert _not_progress(err) == ["occvo run: interrupted"], err
    assert not list(tmp_path.glob("run.rrd*"))


CALLBACK = """
import os, signal, time
from occvo_cli.cli import _Sigint
_Sigint.install()
# code whose frame is in llvmlite, as numba's object-cache callback from compiled code is: a KeyboardInterrupt
# raised there would be printed and swallowed by ctypes
inside = compile("os.kill(os.getpid(), signal.SIGINT)\\nfor _ in range(1000): pass\\nreached = True", os.path.join(os.sep, "x", "llvmlite", "callback.py"), "exec")
scope = {"os": os, "signal": signal}
exec(inside, scope)
print("callback ran to its end:", scope.get("reached"), flush=True)
try:
    for _ in range(600):
        time.sleep(0.05)
    print("no interrupt after the callback", flush=True)
except KeyboardInterrupt:
    print("interrupted after the callback:", _Sigint.received, flush=True)
"""


def test_ctrl_c_inside_a_compiled_codes_callback_arrives_after_it():
    proc = subprocess.run([sys.executable, "-c", CALLBACK], capture_output=True, text=True, env=ENV, timeout=120)
    assert proc.stdout.splitlines() == ["callback ran to its end: True", "interrupted after the callback: True"], (
        proc.stdout + proc.stderr
    )
    assert proc.stderr == ""
