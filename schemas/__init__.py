"""Wire schemas of the occvo services: pydantic models, the msgpack codec and the Zenoh key expressions."""

from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import (
    SCHEMA_VERSION,
    Array,
    CameraFrame,
    CameraImage,
    ErrorEvent,
    GridSpecModel,
    MapInfo,
    MapTile,
    MapTileQuery,
    MapUpdate,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
    Trajectory,
    WorkerHealth,
)

__all__ = [
    "SCHEMA_VERSION",
    "Array",
    "CameraFrame",
    "CameraImage",
    "CodecError",
    "ErrorEvent",
    "GridSpecModel",
    "MapInfo",
    "MapTile",
    "MapTileQuery",
    "MapUpdate",
    "OccupancyFrameMsg",
    "PoseEstimate",
    "SparseOccupancy",
    "Trajectory",
    "WorkerHealth",
    "decode",
    "encode",
]
