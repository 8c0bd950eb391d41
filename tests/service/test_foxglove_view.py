"""`occvo view --foxglove PORT --mcap FILE` follows a running service (router and workers on loopback): a Foxglove
WebSocket client is advertised the channels in Foxglove's schemas and gets the poses it subscribes to as a replay
runs; the MCAP written beside it holds a frame's two transforms (map -> odom, odom -> base_link)."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time

import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk is in the foxglove extra")
ws_client = pytest.importorskip("websockets.sync.client", reason="websockets is in the dev extra")
mcap_reader = pytest.importorskip("mcap.reader", reason="mcap is in the foxglove extra")

CHANNELS = {
    "/tf": "foxglove.FrameTransform",
    "/occvo/odom": "foxglove.PoseInFrame",
    "/occvo/path": "foxglove.PosesInFrame",
    "/occvo/occupancy": "foxglove.PointCloud",
    "/occvo/map": "foxglove.PointCloud",
}
MESSAGE_DATA = 1  # the protocol's binary opcode of a subscribed message


def _json(ws, op: str, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        raw = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        if isinstance(raw, str) and json.loads(raw).get("op") == op:
            return json.loads(raw)


def test_occvo_view_serves_the_stream_to_a_foxglove_client_and_writes_the_mcap(tmp_path):
    from occvo_core.sim import SyntheticScene
    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import replay
    from occvo_services.local import InProcessService

    n, mcap = 4, tmp_path / "view.mcap"
    with InProcessService() as svc:
        viewer = subprocess.Popen(
            [sys.executable, "-m", "occvo_cli", "view", "--connect", svc.endpoint, "--stream", "fox"]
            + ["--foxglove", "0", "--mcap", str(mcap), "--seconds", "300"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            line = viewer.stdout.readline().strip()
            assert line.startswith("foxglove: ws://127.0.0.1:"), viewer.stderr.read()
            with ws_client.connect(line.removeprefix("foxglove: "), subprotocols=["foxglove.sdk.v1"]) as ws:
                assert _json(ws, "serverInfo")["name"] == "occvo"
                advertised = {}
                while set(advertised) != set(CHANNELS):  # one advertise message may hold some channels only
                    advertised |= {c["topic"]: c for c in _json(ws, "advertise")["channels"]}
                assert {t: c["schemaName"] for t, c in advertised.items()} == CHANNELS
                ws.send(
                    json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": advertised["/tf"]["id"]}]})
                )
                with OccVOClient(svc.endpoint, stream="fox") as client:
                    client.wait_for_workers(timeout=120)
                    assert replay(client, SyntheticScene(seed=4, frames=n), timeout=300)["poses"] == n
                got = 0
                while got < n:
                    raw = ws.recv(timeout=60)
                    if isinstance(raw, bytes) and raw[0] == MESSAGE_DATA:
                        assert struct.unpack_from("<I", raw, 1)[0] == 7
                        got += 1
        finally:
            viewer.terminate()
            out, err = viewer.communicate(timeout=60)
    assert viewer.returncode == 0, err
    assert json.loads(out.splitlines()[-1])["poses"] == n
    with open(mcap, "rb") as f:
        summary = mcap_reader.make_reader(f).get_summary()
    counts = {summary.channels[c].topic: k for c, k in summary.statistics.channel_message_counts.items()}
    # /tf: map -> odom and odom -> base_link a frame
    assert counts["/tf"] == 2 * n and counts["/occvo/occupancy"] == n and counts["/occvo/map"] >= 1
    assert {s.name for s in summary.schemas.values()} == set(CHANNELS.values())
