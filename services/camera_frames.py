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
    occupancy = SparseOccupancy.from_points(frame.points, frame.labels, grid, exact)
    # added after validation: pydantic runs a nested model's checks again, voxel by voxel, when it is a field's value
    return CameraFrame(stream=stream, seq=seq, stamp=float(frame.stamp), sent_at=time.time()).model_copy(
        update={"gt_occupancy": occupancy}
    )
