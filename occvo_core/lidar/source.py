"""A nuScenes drive's occupancy from its LiDAR, frame by frame and causally: each keyframe's occupancy from its own
sweep, labelled by the boxes (annotations, as in Occ3D's ground truth) and ground geometry. The geometry is the
sweep's alone: the ground-truth ego pose only places the boxes (annotated in the world) in the sweep to label its
points, and is the scene's ground truth for evaluation; it never reaches the odometry."""

from __future__ import annotations

import numpy as np

from occvo_core.datasets.nuscenes_drive import DriveSource, NuScenesDrive
from occvo_core.frame import OccupancyFrame
from occvo_core.lidar.boxes import boxes_in_frame
from occvo_core.lidar.sweep import label_points, off_the_car, voxel_labels, voxel_means


class LidarOccupancyScene(DriveSource):
    """SceneSource: frame i = the voxels of keyframe i's sweep, ego frame, stamped with the sweep's time."""

    gt_on_map_plane = True  # nuScenes' ego poses keep z = 0 up and down ramps: APE is scored on the plane
    # A sweep's occupancy is thin (rings, one side of each object): a robust kernel, covariances from a wider
    # neighbourhood, flatter, and only voxels seen in 9 of 10 frames since they appeared constrain registration (a
    # ring's voxels come and go as the car moves). Chosen on scene-0916 (docs/datasets.md), beside the release's.
    config_defaults = {
        "gicp": {"robust_kernel_scale": 0.5, "k_neighbours_radius_voxels": 3, "covariance_epsilon": 0.1},
        "voxel_pfilter": {"p_index_threshold": 0.9},
    }

    def __init__(self, drive: NuScenesDrive):
        super().__init__(drive, "lidar")

    @property
    def files(self) -> list:
        """The sweep each frame is made from (run.json's input digest)."""
        return [k.lidar_file for k in self.drive.samples]

    @property
    def stamps(self) -> np.ndarray:
        return np.array([k.lidar_stamp for k in self.drive.samples])

    def labelled_points(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The sweep's points off the car (N,3), ego frame, and their Occ3D classes (N,)."""
        k = self.drive[index]
        points = self.drive.lidar_in_ego(index)
        points = points[off_the_car(points)]
        # boxes are annotated at the sample's instant, the sweep's: placed in its ego frame by the annotation pose
        boxes = boxes_in_frame(self.drive.boxes(index), np.linalg.inv(k.ego_pose))
        return points, label_points(points, boxes)[0]

    def semantics(self, index: int) -> np.ndarray:
        """The sweep's dense label grid (200,200,16)."""
        return voxel_labels(*self.labelled_points(index))

    def __getitem__(self, index: int) -> OccupancyFrame:
        points, labels = self.labelled_points(index)
        occupied, means = voxel_means(points)
        classes = voxel_labels(points, labels).reshape(-1)[occupied]  # never FREE: each of these voxels has points
        meta = {"scene": self.name, "source": "lidar"}
        return OccupancyFrame(means, classes, index, float(self.drive[index].lidar_stamp), meta)
