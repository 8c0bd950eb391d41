"""The ROS 2 messages occvo reads and writes, built and decoded with rosbags' type stores (one per distribution).

Stamps are integer nanoseconds; a frame's stamp in seconds is `ns / 10**9` in exact integer division, which gives the
same float as the recorded microseconds / 1e6 (both are the correctly rounded value of the same fraction)."""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from occvo_core.errors import ConfigError

DISTROS = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
_STORES: dict[str, object] = {}

# PointField datatypes (sensor_msgs/msg/PointField) and their numpy dtypes, little-endian
FIELD_DTYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}


def typestore(distro: str = "jazzy"):
    if distro not in DISTROS:
        raise ConfigError(f"--ros-distro {distro}: one of {', '.join(DISTROS)}")
    if distro not in _STORES:
        _STORES[distro] = get_typestore(DISTROS[distro])
    return _STORES[distro]


def stamp_of(ns: int) -> float:
    """Nanoseconds (int) to seconds (float), correctly rounded."""
    return int(ns) / 1_000_000_000


def ns_of_header(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def header(store, ns: int, frame_id: str):
    T = store.types
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id
    )


def pose_msg(store, M: np.ndarray):
    T = store.types
    x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(M[0, 3]), y=float(M[1, 3]), z=float(M[2, 3])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def transform_msg(store, M: np.ndarray, quaternion=None):
    """quaternion (x, y, z, w): the rotation as its source recorded it, where the matrix was made from one (a
    quaternion made back from the matrix is off in its last bits)."""
    T = store.types
    x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat() if quaternion is None else quaternion
    return T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=float(M[0, 3]), y=float(M[1, 3]), z=float(M[2, 3])),
        rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def matrix(position, orientation) -> np.ndarray:
    """4x4 from a Point/Vector3 and a Quaternion message."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat([orientation.x, orientation.y, orientation.z, orientation.w]).as_matrix()
    M[:3, 3] = position.x, position.y, position.z
    return M


def cloud_msg(store, ns: int, frame_id: str, records: np.ndarray, field_types: dict[str, str]):
    """A PointCloud2 of a structured array; field_types names each field's PointField datatype."""
    T = store.types
    field = T["sensor_msgs/msg/PointField"]
    fields = [
        field(name=n, offset=records.dtype.fields[n][1], datatype=getattr(field, field_types[n]), count=1)
        for n in records.dtype.names
    ]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(store, ns, frame_id),
        height=1,
        width=len(records),
        fields=fields,
        is_bigendian=False,
        point_step=records.dtype.itemsize,
        row_step=records.dtype.itemsize * len(records),
        data=np.frombuffer(records.tobytes(), np.uint8),
        is_dense=True,
    )


def occupancy_records(points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, dict[str, str]]:
    """An occupancy frame as x, y, z float64 (the frame's own coordinates, kept bit for bit) and class uint8."""
    dtype = np.dtype({"names": ["x", "y", "z", "class"], "formats": ["<f8", "<f8", "<f8", "u1"], "itemsize": 25})
    rec = np.zeros(len(points), dtype)
    for i, axis in enumerate("xyz"):
        rec[axis] = points[:, i]
    rec["class"] = labels
    return rec, {"x": "FLOAT64", "y": "FLOAT64", "z": "FLOAT64", "class": "UINT8"}


def cloud_fields(msg, names: tuple[str, ...], where: str) -> list[np.ndarray]:
    """The named fields of a PointCloud2 as arrays (any numeric PointField type); a missing field is a ValueError
    naming what the cloud has."""
    if msg.is_bigendian:
        raise ValueError(f"{where}: a big-endian PointCloud2 is not supported")
    have = {f.name: f for f in msg.fields}
    n = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, np.uint8)
    step = int(msg.point_step)
    if data.size < n * step:
        raise ValueError(f"{where}: {data.size} bytes of data for {n} points of {step} bytes")
    out = []
    for name in names:
        f = have.get(name)
        if f is None or int(f.datatype) not in FIELD_DTYPES:
            raise ValueError(f"{where}: no numeric field {name!r} (the cloud has {sorted(have)})")
        dt = np.dtype(FIELD_DTYPES[int(f.datatype)])
        rows = data[: n * step].reshape(n, step)[:, int(f.offset) : int(f.offset) + dt.itemsize] if n else data[:0]
        out.append(np.ascontiguousarray(rows).view(dt).reshape(n))
    return out
