"""One floating-point environment for every x86-64 machine with AVX2, so recorded figures hold on another machine.

numpy picks its SIMD loops by the CPU when it loads (with AVX-512, sin, cos and exp round differently in the last
bit) and OpenBLAS picks its kernels the same way. One last bit moves a voxel centre into the next voxel and the
trajectories part, so the same seed gives another APE on another CPU. Digests (tests/core/record_digests.py) and
the accuracy benchmark run in a child process with both pinned to the AVX2 level: `pinned_env()` is its environment;
`python -m occvo_core.reproducible occvo run ...` runs any command in it.
"""

from __future__ import annotations

import os
import platform
import sys

CORETYPE = "Haswell"  # OpenBLAS's AVX2 kernels


def _cpu_features() -> tuple[list[str], dict[str, bool]]:
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    return list(__cpu_dispatch__), dict(__cpu_features__)


def pinned_env(base: dict[str, str] | None = None) -> dict[str, str] | None:
    """`base` (default: this process's environment) with numpy's loops above AVX2 switched off and OpenBLAS on its
    AVX2 kernels; None where that level cannot be had (not x86-64, or no AVX2)."""
    env = dict(os.environ if base is None else base)
    if is_pinned():  # numpy here runs without those loops already, so it no longer lists them: pass ours on
        env["NPY_DISABLE_CPU_FEATURES"], env["OPENBLAS_CORETYPE"] = os.environ["NPY_DISABLE_CPU_FEATURES"], CORETYPE
        return env
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    dispatch, features = _cpu_features()
    if not (features.get("X86_V3") or features.get("AVX2")):
        return None
    above = [k for k in dispatch if features.get(k) and ("512" in k or k == "X86_V4")]
    env["NPY_DISABLE_CPU_FEATURES"] = " ".join(above)
    env["OPENBLAS_CORETYPE"] = CORETYPE
    return env


def is_pinned() -> bool:
    """Whether this process started in `pinned_env()` (the pins act only at load time, so only a child can have them)."""
    return os.environ.get("OPENBLAS_CORETYPE") == CORETYPE and "NPY_DISABLE_CPU_FEATURES" in os.environ


def restart_pinned() -> None:
    """Start this Python process again, same arguments, in pinned_env(); nothing where it runs there already or
    cannot (the pins act only when numpy loads, so a process cannot pin itself)."""
    env = pinned_env()
    if env is not None and not is_pinned():
        os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)


def main(argv: list[str]) -> int:
    """`python -m occvo_core.reproducible COMMAND ...`: run a command in the pinned environment."""
    env = pinned_env()
    if not argv or env is None:
        print("usage: python -m occvo_core.reproducible COMMAND ... (x86-64 with AVX2 only)", file=sys.stderr)
        return 2
    os.execvpe(argv[0], argv, env)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
