"""Digests of OccVO's poses and map on fixed scenes, so a refactor can prove it changed no bit.

    PYTHONPATH=$PWD python tests/core/record_digests.py        # re-record tests/core/digests.json

Both recording and checking run in a child process in occvo_core.reproducible's pinned floating-point environment,
so the digests hold on any x86-64 machine with AVX2, whatever its newer vector units.

Re-record only when a change is meant to move poses or maps (e.g. a new default in OccVOConfig), and say so in the
commit. tests/core/test_digests.py checks the code against the recorded file.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

DIGESTS = Path(__file__).with_name("digests.json")
SAMPLE = Path(__file__).resolve().parents[3] / "shared" / "data" / "occvo-sample"
REAL_SCENES = ("scene-0101", "scene-0268")
SYNTHETIC_SEEDS = (0, 1, 2, 3, 4)
SYNTHETIC_FRAMES = 16  # the same length for recording and checking; short enough for one core


def _sha(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def digest_run(frames) -> dict[str, object]:
    """Run OccVO with the default config over frames: sha256 of the poses' bytes and of the final map (points and
    labels, sorted by x, y, z, label so the digest names the map, not its row order)."""
    from occvo_core import OccVO

    vo = OccVO()
    for f in frames:
        vo.step(f)
    points, labels = vo.map_points()
    order = np.lexsort((labels, points[:, 2], points[:, 1], points[:, 0]))
    return {
        "frames": len(vo.poses),
        "poses": _sha(vo.poses.astype(np.float64)),
        "map": _sha(points[order].astype(np.float64), labels[order].astype(np.uint8)),
        "map_voxels": len(points),
    }


def real_frames(name: str):
    from occvo_core.datasets import OccVOReleaseScene

    scene = OccVOReleaseScene(SAMPLE / "occupancy" / name)
    return (scene[i] for i in range(len(scene)))


def synthetic_frames(seed: int):
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=seed, frames=SYNTHETIC_FRAMES)
    return (scene[i] for i in range(len(scene)))


def cases() -> list[str]:
    return [f"real:{n}" for n in REAL_SCENES] + [f"synthetic:{s}" for s in SYNTHETIC_SEEDS]


def compute(case: str) -> dict[str, object]:
    kind, name = case.split(":")
    return digest_run(real_frames(name) if kind == "real" else synthetic_frames(int(name)))


def compute_pinned(names: list[str]) -> dict[str, dict[str, object]]:
    """compute() of each case in the pinned environment: here when this process has it (the test suite does), else in
    a child process (it must hold from numpy's load on)."""
    from occvo_core.reproducible import is_pinned, pinned_env

    if is_pinned():
        return {case: compute(case) for case in names}
    env = pinned_env()
    if env is None:
        raise RuntimeError("the digests' floating-point environment needs an x86-64 CPU with AVX2")
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    child = [sys.executable, __file__, "--print", *names]
    out = subprocess.run(child, env=env, capture_output=True, text=True, timeout=1800, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"digest child failed ({out.returncode}): {out.stderr[-2000:]}")
    return json.loads(out.stdout)


def main() -> int:
    if sys.argv[1:2] == ["--print"]:  # the child: the pins are in place
        from occvo_core.reproducible import is_pinned

        assert is_pinned(), "run through compute_pinned()"
        print(json.dumps({case: compute(case) for case in sys.argv[2:]}))
        return 0
    if not (SAMPLE / "occupancy").is_dir():
        print(f"real sample not found at {SAMPLE}: refusing to record digests without the real scenes", file=sys.stderr)
        return 1
    out = compute_pinned(cases())
    DIGESTS.write_text(json.dumps({"synthetic_frames": SYNTHETIC_FRAMES, "cases": out}, indent=1) + "\n")
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
