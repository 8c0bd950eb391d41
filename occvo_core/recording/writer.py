"""A ROS 2 recording written with rosbags: a bag folder (metadata.yaml + sqlite3 or mcap storage) or one MCAP file,
as `ros2 bag record` writes them, in the bag version of the distribution asked for.

rosbags writes bag versions 8 (Jazzy's) and 9; a Humble bag (version 5, which Humble's rosbag2 reads: it refuses
newer metadata) is written as version 8 and its metadata.yaml rewritten in version 5's layout: no `custom_data`,
`ros_distro` or `type_description_hash`, the same QoS profiles (integer enums, as versions 4-8 write them)."""

from __future__ import annotations

import shutil
import tempfile
from io import StringIO
from pathlib import Path

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from ruamel.yaml import YAML

from occvo_core.errors import ConfigError
from occvo_core.recording.messages import typestore

BAG_VERSION = {"humble": 5, "jazzy": 8}
_UNSET = QosTime(0, 0)  # deadline, lifespan, lease: unspecified, the ROS 2 default


def qos(latched: bool = False, depth: int = 10) -> Qos:
    """Reliable; latched topics (the map, tf_static, a recording's description) transient local, depth 1, so a
    subscriber joining late (RViz, `ros2 bag play`'s subscribers) gets the last message."""
    return Qos(
        QosHistory.KEEP_LAST,
        1 if latched else depth,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        _UNSET,
        _UNSET,
        QosLiveliness.AUTOMATIC,
        _UNSET,
        False,
    )


class RecordingWriter:
    """Messages to `path`: a file ending in .mcap (one MCAP file, as `ros2 bag record --storage mcap` writes inside its
    folder) or a bag folder (`storage` sqlite3 or mcap). The path must not exist yet."""

    def __init__(self, path: str | Path, distro: str = "jazzy", storage: str = "sqlite3", flag: str = "--out"):
        self.path, self.distro = Path(path), distro
        self.store = typestore(distro)
        if self.path.exists():
            raise ConfigError(f"{flag} {self.path}: already exists: remove it or name another")
        if storage not in ("sqlite3", "mcap"):
            raise ConfigError(f"--storage {storage}: sqlite3 or mcap")
        self.single_file = self.path.suffix == ".mcap"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.single_file:  # rosbags writes folders: the MCAP file is taken out of one made beside the target
            self._tmp = Path(tempfile.mkdtemp(prefix=".partial-", dir=self.path.parent))
            folder, plugin = self._tmp / self.path.stem, StoragePlugin.MCAP
        else:
            self._tmp, folder = None, self.path
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self.writer = Writer(folder, version=8, storage_plugin=plugin)
        self.writer.open()
        self.connections: dict[str, tuple[object, str]] = {}

    def add(self, topic: str, msgtype: str, latched: bool = False) -> None:
        conn = self.writer.add_connection(topic, msgtype, typestore=self.store, offered_qos_profiles=[qos(latched)])
        self.connections[topic] = (conn, msgtype)

    def write(self, topic: str, ns: int, msg) -> None:
        conn, msgtype = self.connections[topic]
        self.writer.write(conn, int(ns), self.store.serialize_cdr(msg, msgtype))

    def close(self) -> None:
        if self.writer is None:
            return
        self.writer.close()
        self.writer = None
        if self.single_file:
            (mcap,) = self._tmp.glob("*/*.mcap")
            mcap.replace(self.path)
            shutil.rmtree(self._tmp)
        elif BAG_VERSION[self.distro] != 8:
            _rewrite_metadata(self.path / "metadata.yaml", BAG_VERSION[self.distro])

    def abandon(self) -> None:
        """Nothing half-written left behind."""
        if self.writer is not None:
            self.writer.abort()
            self.writer = None
        for p in (self._tmp, None if self.single_file else self.path):
            if p is not None and p.exists():
                shutil.rmtree(p, ignore_errors=True)


def _rewrite_metadata(path: Path, version: int) -> None:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    doc = yaml.load(path.read_text())
    info = doc["rosbag2_bagfile_information"]
    info["version"] = version
    for key in ("custom_data", "ros_distro"):
        info.pop(key, None)
    for t in info["topics_with_message_count"]:
        t["topic_metadata"].pop("type_description_hash", None)
    out = StringIO()
    yaml.dump(doc, out)
    path.write_text(out.getvalue())
