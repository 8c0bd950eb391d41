"""Follow a running service's stream into a view (RerunView, FoxgloveView, or several as Views): poses, the frames'
occupancy and map tile updates over Zenoh. (Moved objects are not published by the service, so rerun's
world/moved_objects stays empty here.)"""

from __future__ import annotations

import threading

import numpy as np


class StreamFollower:
    """Subscribes to occvo/<stream>/{pose, occupancy, map/updates} on a Zenoh session and logs what arrives;
    a message that does not decode is counted and skipped (the viewer never dies of one)."""

    def __init__(self, session, stream: str, view):
        from occvo_schemas import keys

        self.view, self.stream = view, stream
        self.counts = {"poses": 0, "occupancy": 0, "map_updates": 0, "tiles": 0, "undecodable": 0}
        self._lock = threading.Lock()  # one logger, three subscriber threads
        self._stamp_of: dict[int, float] = {}
        self._subs = [
            session.declare_subscriber(keys.pose(stream), self._on_pose),
            session.declare_subscriber(keys.occupancy(stream), self._on_occupancy),
            session.declare_subscriber(keys.map_updates(stream), self._on_map),
        ]

    def _decode(self, sample, model):
        from occvo_schemas.codec import CodecError, decode

        try:
            return decode(sample.payload.to_bytes(), model)
        except CodecError:
            with self._lock:
                self.counts["undecodable"] += 1
            return None

    def _on_pose(self, sample) -> None:
        from occvo_schemas.models import PoseEstimate

        p = self._decode(sample, PoseEstimate)
        if p is None:
            return
        with self._lock:
            self._stamp_of[p.seq] = p.stamp
            self.view.pose(p.seq, p.stamp, np.asarray(p.pose, np.float64))
            self.view.scalar("registration_ms", sum(p.timings_ms.values()))
            self.counts["poses"] += 1

    def _on_occupancy(self, sample) -> None:
        from occvo_schemas.models import OccupancyFrameMsg

        m = self._decode(sample, OccupancyFrameMsg)
        if m is None:
            return
        with self._lock:
            self.view.time(m.seq, m.stamp)
            self.view.occupancy(m.occupancy.to_points(), m.occupancy.labels.to_numpy())
            self.counts["occupancy"] += 1

    def _on_map(self, sample) -> None:
        from occvo_schemas.models import MapUpdate

        u = self._decode(sample, MapUpdate)
        if u is None:
            return
        with self._lock:
            self.view.time(u.seq, self._stamp_of.get(u.seq, 0.0))
            if u.reset:
                self.view.clear_map()
            for t in u.tiles:
                self.view.map_tile(t.ix, t.iy, t.points.to_numpy(), t.labels.to_numpy())
            getattr(self.view, "map_updated", lambda: None)()
            self.counts["map_updates"] += 1
            self.counts["tiles"] += len(u.tiles)

    def close(self) -> None:
        """Stop following (the view is its owner's to close)."""
        for s in self._subs:
            s.undeclare()
