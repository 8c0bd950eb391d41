"""A nuScenes drive as a ROS 2 recording (MCAP file or bag folder), so the same drive can be run from either form:

  /occvo/occupancy    sensor_msgs/msg/PointCloud2   keyframe i's LiDAR occupancy (LidarOccupancyScene's frame i):
                                                    x, y, z float64 (the frame's coordinates bit for bit), class uint8,
                                                    in base_link, at the sweep's stamp
  /occvo/groundtruth  geometry_msgs/msg/PoseStamped the ego pose at the sweep (base_link -> world), for APE
  /occvo/source       std_msgs/msg/String           JSON: scene name, rate, ground truth on the map plane, and the
                                                    LiDAR source's configuration defaults (latched)
  /CAM_*/image_rect_compressed  sensor_msgs/msg/CompressedImage  the keyframe's JPEG as recorded, at its own stamp
  /CAM_*/camera_info  sensor_msgs/msg/CameraInfo    its intrinsics and size (nuScenes' images are undistorted)
  /tf_static          tf2_msgs/msg/TFMessage        base_link -> each camera and LIDAR_TOP (latched)
Camera topics are named as nuscenes2mcap names them; every message is logged at its header's stamp."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES
from occvo_core.recording import messages as m
from occvo_core.recording.writer import RecordingWriter

EGO_FRAME, WORLD_FRAME = "base_link", "world"
IMAGE_TOPIC, INFO_TOPIC = "/{camera}/image_rect_compressed", "/{camera}/camera_info"


def ns_of_seconds(stamp: float) -> int:
    """nuScenes' stamps are whole microseconds: seconds -> the recorded microseconds -> nanoseconds."""
    return int(round(float(stamp) * 1e6)) * 1000


def recorded_rotations(drive, keyframe) -> dict[str, tuple[float, float, float, float]]:
    """Each sensor's rotation as the drive's calibration records it (x, y, z, w): /tf_static carries it as is, so a
    reader's matrix is the drive's own bit for bit. A quaternion made back from the matrix is off in its last bits,
    and so is the camera model's occupancy (one voxel of 16k at scene-0916's keyframe 1, 2 cm in its pose)."""
    tables = drive.tables
    out = {}
    for channel, sd in tables.keyframes(tables.get("sample", keyframe.token)).items():
        w, x, y, z = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])["rotation"]
        out[channel] = (float(x), float(y), float(z), float(w))
    return out


def convert_drive(source, out: str | Path, distro: str = "jazzy", storage: str = "sqlite3", images: bool = True):
    """`source` a LidarOccupancyScene (its drive's cameras come along when `images`); returns the messages written."""
    drive = source.drive
    w = RecordingWriter(out, distro=distro, storage=storage)
    try:
        count = _write(w, source, drive, images)
    except BaseException:
        w.abandon()
        raise
    w.close()
    return count


def _write(w: RecordingWriter, source, drive, images: bool) -> int:
    T, store, count = w.store.types, w.store, 0
    w.add("/occvo/source", "std_msgs/msg/String", latched=True)
    w.add("/occvo/occupancy", "sensor_msgs/msg/PointCloud2")
    w.add("/occvo/groundtruth", "geometry_msgs/msg/PoseStamped")
    first_ns = ns_of_seconds(drive[0].lidar_stamp)
    info = {
        "name": source.name,
        "drive": drive.name,
        "rate_hz": source.rate_hz,
        "gt_on_map_plane": bool(getattr(source, "gt_on_map_plane", False)),
        "config_defaults": getattr(source, "config_defaults", None),
        "made_from": f"nuScenes {drive.name}, LiDAR occupancy (occvo convert-drive)",
    }
    w.write("/occvo/source", first_ns, T["std_msgs/msg/String"](data=json.dumps(info)))
    count += 1
    if images:
        w.add("/tf_static", "tf2_msgs/msg/TFMessage", latched=True)
        for cam in CAMERA_NAMES:
            w.add(IMAGE_TOPIC.format(camera=cam), "sensor_msgs/msg/CompressedImage")
            w.add(INFO_TOPIC.format(camera=cam), "sensor_msgs/msg/CameraInfo")
        k0 = drive[0]
        frames = [(cam, k0.cam_to_ego[c]) for c, cam in enumerate(CAMERA_NAMES)] + [("LIDAR_TOP", k0.lidar_to_ego)]
        quats = recorded_rotations(drive, k0)
        tfs = [
            T["geometry_msgs/msg/TransformStamped"](
                header=m.header(store, first_ns, EGO_FRAME),
                child_frame_id=name,
                transform=m.transform_msg(store, M, quats.get(name)),
            )
            for name, M in frames
            if M is not None
        ]
        w.write("/tf_static", first_ns, T["tf2_msgs/msg/TFMessage"](transforms=tfs))
        count += 1
    for i in range(len(source)):
        k = drive[i]
        frame = source[i]
        ns = ns_of_seconds(k.lidar_stamp)
        records, types = m.occupancy_records(frame.points, frame.labels)
        w.write("/occvo/occupancy", ns, m.cloud_msg(store, ns, EGO_FRAME, records, types))
        pose = T["geometry_msgs/msg/PoseStamped"](
            header=m.header(store, ns, WORLD_FRAME), pose=m.pose_msg(store, k.ego_pose)
        )
        w.write("/occvo/groundtruth", ns, pose)
        count += 2
        if images:
            count += _write_cameras(w, k)
    return count


def _write_cameras(w: RecordingWriter, k) -> int:
    T, store = w.store.types, w.store
    from occvo_core.datasets.nuscenes_drive import _image_size

    for c, cam in enumerate(CAMERA_NAMES):
        ns = ns_of_seconds(k.camera_stamps[c])
        jpeg = Path(k.files[c]).read_bytes()
        hdr = m.header(store, ns, cam)
        w.write(
            IMAGE_TOPIC.format(camera=cam),
            ns,
            T["sensor_msgs/msg/CompressedImage"](header=hdr, format="jpeg", data=np.frombuffer(jpeg, np.uint8)),
        )
        width, height = _image_size(Path(k.files[c]))
        K = np.asarray(k.intrinsics[c], np.float64)
        P = np.zeros((3, 4))
        P[:, :3] = K
        info = T["sensor_msgs/msg/CameraInfo"](
            header=m.header(store, ns, cam),
            height=height,
            width=width,
            distortion_model="plumb_bob",
            d=np.zeros(5),
            k=K.reshape(9).copy(),
            r=np.eye(3).reshape(9),
            p=P.reshape(12),
            binning_x=0,
            binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        w.write(INFO_TOPIC.format(camera=cam), ns, info)
    return 2 * len(CAMERA_NAMES)
