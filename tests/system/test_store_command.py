"""`occvo store list / export / delete` on a store the service wrote, SQLite and PostgreSQL alike: the streams with
their last seq and map tiles, a stream's trajectory exported equal to its poses, a deleted stream gone from the
trajectory store and the map store while the other stays."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from occvo_cli.cli import main
from occvo_core.trajectory import read_tum
from occvo_services.client import OccVOClient
from occvo_services.local import InProcessService


def _run(capsys, *argv) -> dict:
    assert main(["store", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request, tmp_path):
    if request.param == "sqlite":
        return str(tmp_path / "occvo.sqlite")
    return request.getfixturevalue("pg_url")


def test_store_lists_exports_and_deletes_streams(store_url, scene, tmp_path, capsys):
    poses = {}
    with InProcessService(warm_up=False, store_url=store_url) as svc:
        for stream in ("keep", "drop"):
            with OccVOClient(svc.endpoint, stream, timeout=60) as c:
                c.reset()
                poses[stream] = [c.step(f).matrix() for f in scene[:3]]
        mapper = svc.worker("map")
        deadline = time.monotonic() + 20
        while not all((i := mapper.store.info(s)) and i.last_seq == 2 for s in poses):
            assert time.monotonic() < deadline
            time.sleep(0.05)
    listed = {r["stream"]: r for r in _run(capsys, "list", "--store", store_url)["streams"]}
    assert sorted(listed) == ["drop", "keep"]
    assert all(
        r["last_seq"] == 2 and r["poses"] == 3 and r["map_tiles"] > 0 and r["bytes"] > 0 for r in listed.values()
    )
    assert listed["keep"]["client"] and listed["keep"]["client"] != listed["drop"]["client"]  # one session each

    out = tmp_path / "keep.tum"
    assert _run(capsys, "export", "keep", "--store", store_url, "--out", str(out))["poses"] == 3
    _, exported = read_tum(out)
    assert np.allclose(exported, np.array(poses["keep"]), atol=1e-6)

    deleted = _run(capsys, "delete", "drop", "--store", store_url)
    assert deleted["poses_deleted"] == 3 and deleted["map_tiles_deleted"] == listed["drop"]["map_tiles"]
    assert [r["stream"] for r in _run(capsys, "list", "--store", store_url)["streams"]] == ["keep"]
    assert main(["store", "delete", "drop", "--store", store_url]) == 2  # gone: one line, exit 2
    assert "not in" in capsys.readouterr().err
