"""Every Zenoh key expression occvo uses, in one place. <stream> is one key chunk ([A-Za-z0-9_-.]).

Per stream:
  occvo/<stream>/camera               pub   CameraFrame            client/replay -> inference worker
  occvo/<stream>/occupancy            pub   OccupancyFrameMsg      inference -> registration worker
  occvo/<stream>/pose/v2              pub   PoseEstimate           registration worker -> clients, in seq order
  occvo/<stream>/pose                 pub   PoseEstimate v1        the same poses for clients built before v2
  occvo/<stream>/pose/latest          query -> PoseEstimate        (registration worker; v1 unless ?version=2)
  occvo/<stream>/trajectory           query -> Trajectory          (registration worker)
  occvo/<stream>/map/updates          pub   MapUpdate              registration worker -> map service
  occvo/<stream>/map/tile/<ix>/<iy>   query -> MapTile             (map service); occvo/<stream>/map/tile/*/* = region
  occvo/<stream>/map/info             query -> MapInfo             (map service)
  occvo/<stream>/errors               pub   ErrorEvent             any worker
Per worker:
  occvo/@alive/<role>/<worker>        liveliness token
  occvo/@shard/registration/<n>/<i>/<worker>   liveliness token: this worker registers the streams of shard i of n;
                                      0/0: placement "members", the streams owner_of gives it among the live workers
  occvo/@workers/<worker>/stats       query -> WorkerHealth
"""

from __future__ import annotations

import hashlib
import re
import zlib

ROOT = "occvo"
STREAM_RE = re.compile(r"^[A-Za-z0-9_\-.]{1,64}$")


def check_stream(stream: str) -> str:
    if not STREAM_RE.match(stream):
        raise ValueError(f"stream id {stream!r} must be 1..64 of [A-Za-z0-9_-.]")
    return stream


def camera(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/camera"


def occupancy(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/occupancy"


def pose(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/pose/v2"


def pose_v1(stream: str = "*") -> str:
    """PoseEstimate version 1 (schemas/pose_v1.py), as clients built before version 2 follow it."""
    return f"{ROOT}/{stream}/pose"


def pose_latest(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/pose/latest"


def trajectory(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/trajectory"


def map_updates(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/map/updates"


def map_tile(stream: str = "*", ix: int | str = "*", iy: int | str = "*") -> str:
    return f"{ROOT}/{stream}/map/tile/{ix}/{iy}"


def map_info(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/map/info"


def errors(stream: str = "*") -> str:
    return f"{ROOT}/{stream}/errors"


def alive(role: str = "*", worker: str = "*") -> str:
    return f"{ROOT}/@alive/{role}/{worker}"


def registration_shard(shard: int | str = "*", shards: int | str = "*", worker: str = "*") -> str:
    return f"{ROOT}/@shard/registration/{shards}/{shard}/{worker}"


def parse_registration_shard(key: str) -> tuple[int, int] | None:
    """(shard, shards) of a registration_shard key, None if it is not one."""
    m = re.fullmatch(rf"{ROOT}/@shard/registration/(\d+)/(\d+)/[^/]+", str(key))
    return (int(m[2]), int(m[1])) if m else None


def shard_of(stream: str, shards: int) -> int:
    """The shard whose registration worker owns a stream: a stable hash (CRC-32), the same in every process."""
    return zlib.crc32(stream.encode()) % shards


def owner_of(stream: str, workers) -> str | None:
    """The live worker that owns a stream under placement "members": rendezvous hashing, so a worker that comes or
    goes moves only the streams it takes or had, and every process that sees the same workers agrees."""
    return max(workers, key=lambda w: hashlib.blake2b(f"{w}/{stream}".encode(), digest_size=8).digest(), default=None)


def stats(worker: str = "*") -> str:
    return f"{ROOT}/@workers/{worker}/stats"


def stream_of(key: str) -> str:
    """The stream chunk of a per-stream key ('*' when the key has none)."""
    parts = str(key).split("/")
    return parts[1] if len(parts) > 2 and parts[0] == ROOT and not parts[1].startswith("@") else "*"


def tile_of(key: str) -> tuple[int, int] | None:
    """(ix, iy) of a concrete tile key, None when either index is a wildcard or not an integer."""
    parts = str(key).split("/")
    if len(parts) != 6 or parts[2:4] != ["map", "tile"]:
        return None
    try:
        return int(parts[4]), int(parts[5])
    except ValueError:
        return None
