"""A recorded occupancy frame as the camera-frame message the service's replay source takes."""

from __future__ import annotations

import time

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID, GridSpec
from occvo_schemas.models import CameraFrame, SparseOccupancy


def camera_frame_of(
    frame: OccupancyFrame, stream: str, seq: int, grid: GridSpec = OCC3D_GRID, exact: bool = True
) -> CameraFrame:
    """A recorded occupancy frame as a camera-frame message for the replay source (no images, its occupancy);
    exact keeps the recorded coordinates bit for bit, else they are snapped to compact voxel indices."""
    return CameraFrame(
        stream=stream,
        seq=seq,
        stamp=float(frame.stamp),
        gt_occupancy=SparseOccupancy.from_points(frame.points, frame.labels, grid, exact),
        sent_at=time.time(),
    )
