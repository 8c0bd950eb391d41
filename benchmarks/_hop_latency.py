"""pipeline.py's per-hop transport latency: one occupancy message at a time from a publisher's session through a
router to a subscriber's, encode and decode included."""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh

from occvo_core.grid import OCC3D_GRID
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import Array, OccupancyFrameMsg, SparseOccupancy
from occvo_services.sessions import free_port, open_router, open_session


def hop_latency(n: int = 300, voxels: int = 30000, encoding: str = "axes") -> tuple[np.ndarray, int]:
    """ms from encode+put on one session to decoded message on another, through a router; one message at a time.
    encoding: a recorded frame's exact coordinates as float64 "points" or as indices with "axes" (what replay
    sends), or "voxels" (indices only: the network's output)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    pub_s, sub_s = open_session(ep), open_session(ep)
    rng = np.random.default_rng(0)
    # distinct voxels: a frame is a set of voxels, each once (the codec refuses duplicates)
    flat = rng.choice(int(np.prod(OCC3D_GRID.shape)), voxels, replace=False)
    idx = np.stack(np.unravel_index(flat, OCC3D_GRID.shape), axis=1)
    wobble = rng.integers(-3, 4, (3, max(OCC3D_GRID.shape))) * 2.0**-48  # the release's last bits, one value an index
    points = OCC3D_GRID.centres_of(idx) + np.stack([wobble[a, idx[:, a]] for a in range(3)], axis=1)
    labels = rng.integers(0, 17, voxels)
    if encoding == "points":
        occ = SparseOccupancy(points=Array.from_numpy(points), labels=Array.from_numpy(labels.astype(np.uint8)))
    else:
        occ = SparseOccupancy.from_points(points, labels, OCC3D_GRID, exact=encoding == "axes")
    msg = OccupancyFrameMsg(stream="bench", seq=0, stamp=0.0, source="replay", occupancy=occ)
    got = threading.Event()
    lat = []

    def on(sample):
        m = decode(sample.payload.to_bytes(), OccupancyFrameMsg)
        lat.append((time.perf_counter() - t0) * 1000.0)
        assert len(m.occupancy) == voxels
        got.set()

    sub = sub_s.declare_subscriber(keys.occupancy("bench"), on)
    pub = pub_s.declare_publisher(keys.occupancy("bench"), congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.5)
    for i in range(n + 20):  # the first 20 warm the path up
        got.clear()
        t0 = time.perf_counter()
        pub.put(encode(msg.model_copy(update={"seq": i})))
        if not got.wait(5):
            raise RuntimeError("hop benchmark: message lost")
    sub.undeclare()
    pub.undeclare()
    pub_s.close()
    sub_s.close()
    router.close()
    return np.array(lat[20:]), len(encode(msg))
