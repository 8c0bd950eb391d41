"""ROS 2 messages built from occvo's poses and clouds with rosbags' typestore (the `ros` extra): one place for the
bag writer (ros2_bag.py) and the live ROS 2 node (occvo_services/ros2), so both send the same messages."""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from occvo_core.grid import CLASS_COLORS

STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
POINT = np.dtype(
    {"names": ["x", "y", "z", "rgb", "class"], "formats": ["<f4", "<f4", "<f4", "<u4", "u1"], "itemsize": 20}
)
FIELD_TYPES = {"x": "FLOAT32", "y": "FLOAT32", "z": "FLOAT32", "rgb": "FLOAT32", "class": "UINT8"}


def header(ns: int, frame_id: str):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id
    )


def pose(M: np.ndarray):
    x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def odometry(ns: int, M: np.ndarray, frame_id: str, child_frame_id: str):
    """nav_msgs/Odometry of a 4x4 pose; covariances zero (no estimate yet), twist zero."""
    zero6 = np.zeros(36)
    v = T["geometry_msgs/msg/Vector3"]
    return T["nav_msgs/msg/Odometry"](
        header=header(ns, frame_id),
        child_frame_id=child_frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(np.asarray(M, np.float64)), covariance=zero6),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=v(x=0.0, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=0.0)),
            covariance=zero6.copy(),
        ),
    )


def transform(ns: int, M: np.ndarray, frame_id: str, child_frame_id: str):
    """tf2_msgs/TFMessage with the one transform frame_id -> child_frame_id."""
    M = np.asarray(M, np.float64)
    t = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]), rotation=pose(M).orientation
    )
    stamped = T["geometry_msgs/msg/TransformStamped"](
        header=header(ns, frame_id), child_frame_id=child_frame_id, transform=t
    )
    return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def pose_stamped(ns: int, M: np.ndarray, frame_id: str):
    return T["geometry_msgs/msg/PoseStamped"](header=header(ns, frame_id), pose=pose(np.asarray(M, np.float64)))


def point_cloud(ns: int, frame_id: str, points: np.ndarray, labels: np.ndarray):
    """x, y, z float32, rgb (RViz's packed 0x00RRGGBB, the class colour), class uint8 (Occ3D id)."""
    rec = np.zeros(len(points), POINT)
    for i, axis in enumerate("xyz"):
        rec[axis] = points[:, i]
    c = CLASS_COLORS[np.asarray(labels, np.int64)].astype(np.uint32)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]  # read as float32 bits, as RViz does
    rec["class"] = labels
    field = T["sensor_msgs/msg/PointField"]
    fields = [
        field(name=n, offset=POINT.fields[n][1], datatype=getattr(field, FIELD_TYPES[n]), count=1) for n in POINT.names
    ]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(ns, frame_id),
        height=1,
        width=len(rec),
        fields=fields,
        is_bigendian=False,
        point_step=POINT.itemsize,
        row_step=POINT.itemsize * len(rec),
        data=np.frombuffer(rec.tobytes(), np.uint8),
        is_dense=True,
    )
