"""ROS 2 input messages as occvo frames: an occupancy cloud (sensor_msgs/PointCloud2: x, y, z and a class field) as
an OccupancyFrame; six camera images with their CameraInfo and the cameras' /tf_static transforms as a CameraFrame."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.frame import OccupancyFrame
from occvo_schemas.models import CameraFrame, CameraImage

# sensor_msgs/PointField datatype -> numpy type
POINT_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def cloud_frame(msg, class_field: str = "class", index: int = 0) -> OccupancyFrame:
    """The cloud's points (x, y, z as float64) and classes; ValueError names what is wrong with it."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z", class_field) if n not in fields]
    if missing:
        raise ValueError(f"PointCloud2 without field(s) {', '.join(missing)} (has {', '.join(fields) or 'none'})")
    n, step = int(msg.width) * int(msg.height), int(msg.point_step)
    data = np.asarray(msg.data, np.uint8)
    if step <= 0 or n * step > data.size:
        raise ValueError(f"PointCloud2 of {n} points of {step} bytes has {data.size} bytes of data")
    order = ">" if msg.is_bigendian else "<"
    dtypes = {}
    for name in ("x", "y", "z", class_field):
        f = fields[name]
        if f.datatype not in POINT_TYPES or f.offset + np.dtype(POINT_TYPES[f.datatype]).itemsize > step:
            raise ValueError(f"PointCloud2 field {name}: datatype {f.datatype} at offset {f.offset} does not fit")
        dtypes[name] = (order + POINT_TYPES[f.datatype], f.offset)
    if any(dtypes[a][0][1] != "f" for a in "xyz") or dtypes[class_field][0][1] == "f":
        raise ValueError("PointCloud2: x, y, z must be float32 or float64 and the class field an integer")
    rows = int(msg.row_step) if msg.height > 1 else n * step
    if msg.height > 1 and rows != msg.width * step:
        data = data[: rows * msg.height].reshape(msg.height, rows)[:, : msg.width * step].reshape(-1)
    rec = np.frombuffer(
        data[: n * step].tobytes(),
        np.dtype(
            {
                "names": list(dtypes),
                "formats": [d for d, _ in dtypes.values()],
                "offsets": [o for _, o in dtypes.values()],
                "itemsize": step,
            }
        ),
    )
    points = np.stack([rec[a].astype(np.float64) for a in "xyz"], axis=1)
    classes = rec[class_field].astype(np.int64)
    if classes.size and (classes.min() < 0 or classes.max() > 255):
        raise ValueError(f"PointCloud2 classes outside 0..255: {classes.min()}..{classes.max()}")
    return OccupancyFrame(points, classes.astype(np.uint8), index=index, stamp=stamp_ns(msg.header) / 1e9)


def transform_matrix(t) -> np.ndarray:
    """geometry_msgs/Transform as a 4x4 matrix."""
    M = np.eye(4)
    q = t.rotation
    M[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    M[:3, 3] = [t.translation.x, t.translation.y, t.translation.z]
    return M


class CameraSet:
    """Collects the cameras' latest image, CameraInfo and camera -> base transform; a frame once every camera has an
    image newer than the last frame's (stamped with the first camera's image). A camera seen again before the others
    came means an image was lost (rmw_zenoh's keep-last publishers drop samples when the subscriber falls behind):
    the incomplete set is refused with the cameras it lacks, and this image starts the next, so a frame is never made
    of two instants and one lost image costs one frame, not every frame after it."""

    def __init__(self, cameras: list[str], base_frame: str, raw: bool = False):
        self.cameras, self.base_frame, self.raw = list(cameras), base_frame, raw
        self.images: dict[str, object] = {}
        self.intrinsics: dict[str, list] = {}
        self.extrinsics: dict[str, np.ndarray] = {}
        self.stamp_ns = 0  # the last frame's stamp, its first camera's, in ns

    def on_info(self, camera: str, msg) -> None:
        K = np.asarray(msg.k, np.float64).reshape(3, 3)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"CameraInfo of {camera}: K is not a pinhole matrix: {K.tolist()}")
        self.intrinsics[camera] = K.tolist()

    def on_tf_static(self, msg) -> None:
        for t in msg.transforms:  # base -> camera: the camera's pose in the base frame, camera-to-ego
            if t.header.frame_id == self.base_frame:
                self.extrinsics[t.child_frame_id] = transform_matrix(t.transform)

    def on_image(self, camera: str, msg) -> CameraFrame | None:
        lost = [c for c in self.cameras if c not in self.images] if camera in self.images else []
        if lost:
            self.images.clear()
        self.images[camera] = msg
        if lost:
            raise ValueError(f"no image of {', '.join(lost)} before {camera}'s next: the frame they lack is dropped")
        if len(self.images) < len(self.cameras):
            return None
        missing = [c for c in self.cameras if c not in self.intrinsics or self._frame_id(c) not in self.extrinsics]
        if missing:
            raise ValueError(f"no CameraInfo or {self.base_frame} -> camera transform yet for {', '.join(missing)}")
        images = [self._image(c, self.images[c]) for c in self.cameras]
        self.stamp_ns = stamp_ns(self.images[self.cameras[0]].header)
        self.images.clear()
        return CameraFrame(stream="ros2", seq=0, stamp=images[0].stamp, images=images)

    def _frame_id(self, camera: str) -> str:
        return self.images[camera].header.frame_id or camera

    def _image(self, camera: str, msg) -> CameraImage:
        if self.raw:
            if msg.encoding != "rgb8":
                raise ValueError(f"{camera}: raw images must be rgb8, not {msg.encoding}")
            width, height, encoding = int(msg.width), int(msg.height), "raw_rgb8"
        else:
            fmt = msg.format.lower()  # "jpeg", or image_transport's "rgb8; jpeg compressed bgr8"
            encoding = "jpeg" if ("jpeg" in fmt or "jpg" in fmt) else "png" if "png" in fmt else None
            if encoding is None:
                raise ValueError(f"{camera}: compressed images must be jpeg or png, not {msg.format!r}")
            width, height = self._size(msg.data)
        return CameraImage(
            camera=camera,
            encoding=encoding,
            width=width,
            height=height,
            data=bytes(np.asarray(msg.data, np.uint8)),
            intrinsics=self.intrinsics[camera],
            extrinsics=self.extrinsics[self._frame_id(camera)].tolist(),
            stamp=stamp_ns(msg.header) / 1e9,
        )

    @staticmethod
    def _size(data) -> tuple[int, int]:
        import io

        from PIL import Image

        with Image.open(io.BytesIO(bytes(np.asarray(data, np.uint8)))) as im:
            return im.width, im.height
