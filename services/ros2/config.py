"""The ROS 2 node's settings: domain, namespace, which input, topic names, frames (`occvo serve --ros2`, a json5
file for `--ros2-config` or the `ros2` worker of `occvo up`)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from occvo_core.cameras import CAMERA_NAMES
from occvo_services.ros2.names import resolve


class Ros2Topics(BaseModel):
    model_config = ConfigDict(extra="forbid")
    occupancy: str = Field("/occvo/occupancy", description="sensor_msgs/PointCloud2 in: x, y, z and a class field")
    camera_image: str = Field(
        "/{camera}/image_rect_compressed", description="each camera's images ({camera}: CAM_FRONT, ...; nuscenes2mcap)"
    )
    camera_info: str = Field("/{camera}/camera_info", description="each camera's sensor_msgs/CameraInfo")
    tf_static: str = "/tf_static"
    odom: str = Field("/occvo/odom", description="nav_msgs/Odometry out, odom -> base_link")
    tf: str = "/tf"
    path: str = Field("/occvo/path", description="nav_msgs/Path out")
    map: str = Field("/occvo/map", description="sensor_msgs/PointCloud2 out, latched (transient local)")


class Ros2NodeConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID")
    namespace: str = Field("/", pattern=r"^/([A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*)?$")
    node_name: str = Field("occvo", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    input: Literal["occupancy", "cameras"] = Field("occupancy", description="which ROS input feeds the odometry")
    images: Literal["compressed", "raw"] = Field(
        "compressed", description="camera topics carry sensor_msgs/CompressedImage (jpeg, png) or Image (rgb8)"
    )
    cameras: list[str] = Field(list(CAMERA_NAMES), min_length=6, max_length=6, description="in the model's order")
    stream: str | None = Field(None, description="the service stream it feeds (default ros2-<input>)")
    class_field: str = Field("class", description="the PointCloud2 field with each point's Occ3D class")
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    map_every: int = Field(5, ge=1, description="the map is published every this many poses")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO", description="DEBUG: a line per frame sent and per odometry published"
    )
    topics: Ros2Topics = Ros2Topics()

    @classmethod
    def load(cls, path: str | Path | None, **overrides) -> Ros2NodeConfig:
        from occvo_core import config_file

        data = config_file.read(Path(path)) if path else {}
        data.update({k: v for k, v in overrides.items() if v is not None})
        return config_file.validate(cls, data, path or "ros2 settings")

    @property
    def stream_name(self) -> str:
        return self.stream or f"ros2-{self.input}"

    def inputs(self) -> list[str]:
        """The topics the node subscribes, under its namespace: the clouds, or the cameras and /tf_static."""
        t = self.topics
        if self.input == "occupancy":
            names = [t.occupancy]
        else:
            names = [t.tf_static, *(n.format(camera=c) for c in self.cameras for n in (t.camera_info, t.camera_image))]
        return [resolve(n, self.namespace) for n in names]

    def outputs(self) -> list[str]:
        """The topics the node publishes, under its namespace."""
        t = self.topics
        return [resolve(n, self.namespace) for n in (t.odom, t.tf, t.path, t.map)]
