"""A registration or map host needs no torch, open3d or psutil: in a fresh interpreter the router, the registration
worker and the map service register frames, publish poses and answer a tile query, and none of those modules is
ever imported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SCRIPT = r"""
import json, sys, threading
from occvo_core.sim import SyntheticScene
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import OccupancyFrameMsg, PoseEstimate, SparseOccupancy
from occvo_core.grid import OCC3D_GRID
from occvo_services.local import WORKERS, wait_alive
from occvo_services.map_service import MapService
from occvo_services.registration_worker import RegistrationWorker
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import free_port, open_router, open_session
from occvo_services.wire import blocking

endpoint = f"tcp/127.0.0.1:{free_port()}"
router = open_router(endpoint)
workers = [cls(WorkerConfig(connect=endpoint, log_level="WARNING", worker_id=f"{cls.role}-lean")).start()
           for cls in (MapService, RegistrationWorker)]
session = open_session(endpoint)
wait_alive(session, ["registration", "map"], 120.0)
poses, done = [], threading.Event()
def on_pose(sample):
    poses.append(decode(sample.payload.to_bytes(), PoseEstimate).seq)
    if len(poses) == 3:
        done.set()
sub = session.declare_subscriber(keys.pose("lean"), on_pose)
scene = SyntheticScene(seed=1, frames=3)
for i in range(3):
    f = scene[i]
    occ = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID)
    msg = OccupancyFrameMsg(stream="lean", seq=i, stamp=float(f.stamp), source="replay", occupancy=occ)
    session.put(keys.occupancy("lean"), encode(msg), **blocking("occupancy_frame"))
assert done.wait(300), poses
tiles = [r for r in session.get(keys.map_tile("lean", 0, 0), timeout=30.0) if r.ok is not None]
print(json.dumps({"poses": sorted(poses), "tiles": len(tiles),
                  "imported": sorted(m for m in ("torch", "open3d", "psutil") if m in sys.modules)}))
sub.undeclare(); session.close()
for w in workers:
    w.stop()
router.close()
"""


def test_registration_and_map_workers_run_without_torch_open3d_or_psutil():
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["poses"] == [0, 1, 2] and report["tiles"] >= 1
    assert report["imported"] == []
