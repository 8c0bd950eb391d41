"""The client as a newcomer meets it, on real Zenoh sessions (router and workers as threads of this process): the
README's Python snippets run as written against a running service, and a pose's stage timings add up (a stage
includes its own stages)."""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

import pytest

from occvo_services.client import OccVOClient
from occvo_services.local import InProcessService

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO.parent / "shared" / "data" / "occvo-sample" / "occupancy" / "scene-0268"


@pytest.fixture(scope="module")
def service():
    with InProcessService() as svc:
        yield svc


def _readme_python(containing: str) -> str:
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    (block,) = [b for b in blocks if containing in b]
    return block


def test_the_readme_snippets_run_as_written(service, monkeypatch, capsys):
    if not SAMPLE.is_dir():
        pytest.skip(f"real nuScenes sample not found at {SAMPLE} (the README's snippet reads it)")
    monkeypatch.chdir(REPO)  # the README's relative path to the sample, as a user in the checkout runs it
    offline, client = _readme_python("open_scene("), _readme_python("OccVOClient(")
    assert '"tcp/127.0.0.1:7447"' in client
    names: dict = {}
    exec(compile(offline, "README.md (Python)", "exec"), names)
    exec(compile(client.replace('"tcp/127.0.0.1:7447"', repr(service.endpoint)), "README.md (client)", "exec"), names)
    assert names["pose"].seq == len(names["scene"]) - 1
    assert len(names["tile"].points.to_numpy()) > 0
    printed = capsys.readouterr().out  # the tile under the car, when its map had not come yet: the error, caught
    assert printed == "" or "tile_not_found" in printed, printed


def _children(timings: dict) -> dict[str, float]:
    """Each stage's own stages' times summed: `a.b` and `a.c` under `a`."""
    summed: dict[str, float] = defaultdict(float)
    for key, ms in timings.items():
        if "." in key:
            summed[key.rsplit(".", 1)[0]] += ms
    return summed


def test_each_stage_of_a_pose_includes_its_own_stages(service, scene):
    with OccVOClient(service.endpoint, stream="newcomer") as env:
        env.reset()
        poses = [env.step(f) for f in scene[:3]]  # the first frame (preprocess alone) and two registered ones
    for pose in poses:
        children = _children(pose.timings_ms)
        assert "registration" in children and "registration.preprocess" in pose.timings_ms
        for parent, ms in children.items():
            assert pose.timings_ms[parent] >= ms, (pose.seq, parent, pose.timings_ms)
