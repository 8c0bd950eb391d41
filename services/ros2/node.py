"""occvo's ROS 2 node: the ROS input (occupancy clouds or six cameras) fed as one stream of the running service
through OccVOClient, and each pose published as it comes: nav_msgs/Odometry and /tf (odom -> base_link),
nav_msgs/Path, and the service's map as a latched PointCloud2 every `map_every` poses."""

from __future__ import annotations

import logging
import threading

import numpy as np
import zenoh

from occvo_core.viz import ros_messages as rm
from occvo_core.viz.odom_frames import OdomFrames
from occvo_core.viz.ros2_bag import PATH_WINDOW
from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode
from occvo_schemas.models import ErrorEvent, PoseEstimate
from occvo_services.client import OccVOClient
from occvo_services.ros2.config import Ros2NodeConfig
from occvo_services.ros2.graph import Ros2Graph
from occvo_services.ros2.inputs import CameraSet, cloud_frame, stamp_ns
from occvo_services.ros2.names import LATCHED_QOS, SENSOR_QOS
from occvo_services.telemetry import log_event


class OccVONode:
    def __init__(self, session: zenoh.Session, config: Ros2NodeConfig, log: logging.Logger, login: str | None = None):
        """login: the occvo login `session` logged in as (its stream ids carry its prefix), None: anonymous."""
        self.config, self.log = config, log
        self.graph = Ros2Graph(session, config.domain_id, config.node_name, config.namespace, log)
        self.client = OccVOClient(session=session, stream=config.stream_name, login=login)
        self.client.reset()  # this node's first frame starts a new trajectory and map
        self._seq = 0  # the next frame's seq: this node is its stream's one sender
        self._stamps: dict[int, int] = {}  # seq -> the input's header stamp (ns), for the outputs' headers
        self._path: list = []  # (ns, pose) of the last PATH_WINDOW poses
        self._published = 0
        self._last_seq = -1  # the last seq whose odometry went out: a resent frame's pose comes again
        self._out = threading.Lock()  # not _lock: a send under _lock may wait for a pose
        self._frames = OdomFrames()  # twist from consecutive poses
        self._lock = threading.Lock()
        self._map_busy = threading.Lock()
        t = config.topics
        self.odom = self.graph.publisher(t.odom, "nav_msgs/msg/Odometry", SENSOR_QOS)
        self.tf = self.graph.publisher(t.tf, "tf2_msgs/msg/TFMessage", SENSOR_QOS)
        self.path = self.graph.publisher(t.path, "nav_msgs/msg/Path", SENSOR_QOS)
        self.map = self.graph.publisher(t.map, "sensor_msgs/msg/PointCloud2", LATCHED_QOS)
        self._subs = [
            session.declare_subscriber(keys.pose(self.client.stream), self._on_pose),
            session.declare_subscriber(keys.errors(self.client.stream), self._on_error),
        ]
        if config.input == "occupancy":
            self.graph.subscribe(t.occupancy, "sensor_msgs/msg/PointCloud2", self._on_cloud, SENSOR_QOS)
        else:
            self._subscribe_cameras()

    def _subscribe_cameras(self) -> None:
        c, t = self.config, self.config.topics
        self.cameras = CameraSet(c.cameras, c.base_frame, raw=c.images == "raw")
        image_type = "sensor_msgs/msg/Image" if c.images == "raw" else "sensor_msgs/msg/CompressedImage"
        self.graph.subscribe(
            t.tf_static, "tf2_msgs/msg/TFMessage", self._locked(self.cameras.on_tf_static), LATCHED_QOS
        )
        for cam in c.cameras:
            on_info = self._locked(lambda m, cam=cam: self.cameras.on_info(cam, m))
            self.graph.subscribe(t.camera_info.format(camera=cam), "sensor_msgs/msg/CameraInfo", on_info, SENSOR_QOS)
            on_image = self._locked(lambda m, cam=cam: self._on_image(cam, m))
            self.graph.subscribe(t.camera_image.format(camera=cam), image_type, on_image, SENSOR_QOS)

    def _on_image(self, camera: str, msg) -> None:
        frame = self.cameras.on_image(camera, msg)
        if frame is not None:
            self._send(frame, self.cameras.stamp_ns)

    def _locked(self, fn):
        def call(msg):
            with self._lock:
                fn(msg)

        return call

    # -- in
    def _on_cloud(self, msg) -> None:
        with self._lock:
            self._send(cloud_frame(msg, self.config.class_field, index=self._seq), stamp_ns(msg.header))

    def _send(self, frame, ns: int) -> None:
        """Under _lock: frames leave in the order they came; ns, the input's stamp, goes on the outputs."""
        self._stamps[self._seq] = ns  # before the frame leaves: its pose may come back before publish() returns
        self.client.publish(frame)
        log_event(self.log, "frame sent", logging.DEBUG, seq=self._seq, stamp_ns=ns)
        self._seq += 1

    # -- out
    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
        except CodecError:
            return
        if pose.status == "relocalised":  # a loop closure moves the map, never odom -> base_link (REP 105)
            return
        with self._out:  # poses come in seq order; a frame the client sent again is answered again: publish once
            if pose.seq <= self._last_seq:
                return
            self._last_seq = pose.seq
        ns = self._stamps.pop(pose.seq, None)
        ns = round(pose.stamp * 1e9) if ns is None else ns
        M = np.asarray(pose.pose, np.float64)
        c = self.config
        cov = None if pose.covariance is None else np.asarray(pose.covariance, np.float64)
        self.odom.publish(rm.odometry(self._frames, ns, M, c.odom_frame, c.base_frame, cov))
        self.tf.publish(rm.transform(ns, M, c.odom_frame, c.base_frame))
        self._published += 1
        log_event(self.log, "odometry published", logging.DEBUG, seq=pose.seq, stamp_ns=ns)
        self._path = [*self._path[-(PATH_WINDOW - 1) :], (ns, M)]  # the window /occvo/path sends, no more
        self.path.publish(rm.path(ns, self._path, c.odom_frame))
        self.client.forget(pose.seq)  # the node runs for hours: its client keeps nothing it has sent on
        if self._published % c.map_every == 0 and self._map_busy.acquire(blocking=False):
            threading.Thread(target=self._publish_map, args=(ns,), name="occvo-ros2-map", daemon=True).start()

    def _publish_map(self, ns: int) -> None:
        try:
            points, labels = self.client.map_points()
            self.map.publish(rm.point_cloud(ns, self.config.odom_frame, points, labels))
        except Exception as exc:  # noqa: BLE001 - the map service away: the next map goes out later
            log_event(self.log, "map not published", logging.WARNING, error=str(exc)[:200])
        finally:
            self._map_busy.release()

    def _on_error(self, sample: zenoh.Sample) -> None:
        try:
            e = decode(sample.payload.to_bytes(), ErrorEvent)
        except CodecError:
            return
        log_event(self.log, "frame refused", logging.WARNING, seq=e.seq, code=e.code, message=e.message[:300])

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.graph.close()
        self.client.close()
