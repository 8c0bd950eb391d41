"""The live ROS 2 node's messages (occvo_services/ros2), built from the same pieces as the recordings'
(occvo_core/recording/messages.py, viz/ros2_bag.py's point clouds, viz/odom_frames.py's REP 105 frames and twist), so
the node and a bag say the same thing."""

from __future__ import annotations

import numpy as np

from occvo_core.recording import messages as m
from occvo_core.viz.odom_frames import OdomFrames
from occvo_core.viz.ros2_bag import PATH_WINDOW
from occvo_core.viz.ros2_bag import point_cloud as _cloud

STORE = m.typestore("jazzy")
T = STORE.types


def header(ns: int, frame_id: str):
    return m.header(STORE, ns, frame_id)


def odometry(frames: OdomFrames, ns: int, M: np.ndarray, frame_id: str, child_frame_id: str, covariance=None):
    """nav_msgs/Odometry of a 4x4 pose through `frames` (twist from the pose before), with the pose's 6x6
    covariance (rotation, translation in base_link, as StepResult.covariance) as the bag writer puts it; a pose
    without one (degenerate, or from a service before version 2) is given as unknown (1e6), never zero."""
    odom, pose_cov, (linear, angular), twist_cov = frames.update(M, ns, covariance)
    v = T["geometry_msgs/msg/Vector3"]
    return T["nav_msgs/msg/Odometry"](
        header=header(ns, frame_id),
        child_frame_id=child_frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=m.pose_msg(STORE, odom), covariance=pose_cov.reshape(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=v(*map(float, linear)), angular=v(*map(float, angular))),
            covariance=twist_cov.reshape(36),
        ),
    )


def transform(ns: int, M: np.ndarray, frame_id: str, child_frame_id: str):
    """tf2_msgs/TFMessage with the one transform frame_id -> child_frame_id."""
    stamped = T["geometry_msgs/msg/TransformStamped"](
        header=header(ns, frame_id), child_frame_id=child_frame_id, transform=m.transform_msg(STORE, M)
    )
    return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def path(ns: int, poses: list, frame_id: str):
    """nav_msgs/Path of the last PATH_WINDOW poses (a message's size stays bounded however long the drive)."""
    stamped = [
        T["geometry_msgs/msg/PoseStamped"](header=header(t, frame_id), pose=m.pose_msg(STORE, M)) for t, M in poses
    ]
    return T["nav_msgs/msg/Path"](header=header(ns, frame_id), poses=stamped[-PATH_WINDOW:])


def point_cloud(ns: int, frame_id: str, points: np.ndarray, labels: np.ndarray):
    """x, y, z float32, rgb (RViz's packed 0x00RRGGBB, the class colour), class uint8 (Occ3D id)."""
    return _cloud(STORE, ns, frame_id, points, labels)
