"""A ROS 2 recording as input: one MCAP file or a bag folder (metadata.yaml + sqlite3 or mcap storage), CDR messages
as `ros2 bag record` writes them, read with rosbags (no ROS install). The messages of the topics asked for are read
once, raw, in log-time order; each is decoded when used."""

from __future__ import annotations

from pathlib import Path

from occvo_core.errors import DatasetError


def is_recording(path: str | Path) -> bool:
    path = Path(path)
    return (path.is_file() and path.suffix == ".mcap") or (path.is_dir() and (path / "metadata.yaml").is_file())


class Recording:
    """The raw messages of some topics of a recording: `messages[topic]` = [(log ns, CDR bytes)], `types[topic]`."""

    def __init__(self, path: str | Path, topics: list[str], required: dict[str, str]):
        """`required`: topic -> the flag that renames it, for the one line a missing topic gives."""
        from rosbags.rosbag2 import Reader

        from occvo_core.recording.messages import typestore

        self.path, self.store = Path(path), typestore("jazzy")
        try:
            with Reader(self.path) as reader:
                have = {c.topic: c.msgtype for c in reader.connections}
                for topic, flag in required.items():
                    if topic not in have:
                        listed = ", ".join(sorted(have)) or "none"
                        raise DatasetError(self.path, f"no topic {topic} (its topics: {listed}); {flag} names another")
                wanted = [c for c in reader.connections if c.topic in topics]
                self.types = {c.topic: c.msgtype for c in wanted}
                self.messages: dict[str, list[tuple[int, bytes]]] = {t: [] for t in topics}
                for conn, ns, raw in reader.messages(connections=wanted):
                    self.messages[conn.topic].append((int(ns), bytes(raw)))
        except DatasetError:
            raise
        except Exception as exc:  # rosbags' own errors, a truncated file, a broken sqlite database
            why = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise DatasetError(self.path, f"not a readable ROS 2 recording (MCAP file or bag folder): {why}") from None

    def expect(self, topic: str, *msgtypes: str) -> None:
        got = self.types.get(topic)
        if got is not None and got not in msgtypes:
            raise DatasetError(self.path, f"topic {topic} is {got}, not {' or '.join(msgtypes)}")

    def decode(self, topic: str, i: int):
        return self.store.deserialize_cdr(self.messages[topic][i][1], self.types[topic])

    def decoded(self, topic: str) -> list:
        return [self.decode(topic, i) for i in range(len(self.messages.get(topic, [])))]
