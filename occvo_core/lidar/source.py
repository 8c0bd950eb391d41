"""A nuScenes drive's occupancy from its LiDAR, frame by frame and causally: each keyframe's occupancy from its own
sweep, labelled by the boxes (annotations, as in Occ3D's ground truth) and ground geometry. No pose reaches it: the
ground-truth ego poses are only the scene's ground truth, for evaluation."""

from __future__ import annotations

import numpy as np

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import grid_to_points
from occvo_core.lidar.boxes import boxes_in_frame
from occvo_core.lidar.sweep import label_points, off_the_car, voxel_labels


class LidarOccupancyScene:
    """SceneSource: frame i = the voxels of keyframe i's sweep, ego frame, stamped with the sweep's time."""

    def __init__(self, drive: NuScenesDrive):
        self.drive = drive
        self.name, self.rate_hz = f"{drive.name}-lidar", drive.rate_hz

    def __len__(self) -> int:
        return len(self.drive)

    @property
    def gt_poses(self) -> np.ndarray:
        return self.drive.gt_poses

    @property
    def stamps(self) -> np.ndarray:
        return np.array([k.lidar_stamp for k in self.drive.samples])

    def semantics(self, index: int) -> np.ndarray:
        """The sweep's dense label grid (200,200,16)."""
        k = self.drive[index]
        points = self.drive.lidar_in_ego(index)
        points = points[off_the_car(points)]
        # boxes are annotated at the sample's instant, the sweep's: placed in its ego frame by the annotation pose
        boxes = boxes_in_frame(self.drive.boxes(index), np.linalg.inv(k.ego_pose))
        labels, _ = label_points(points, boxes)
        return voxel_labels(points, labels)

    def __getitem__(self, index: int) -> OccupancyFrame:
        points, labels = grid_to_points(self.semantics(index))
        meta = {"scene": self.name, "source": "lidar"}
        return OccupancyFrame(points, labels, index, float(self.drive[index].lidar_stamp), meta)
