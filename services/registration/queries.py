"""Queries: a stream's latest pose and its trajectory, answered by the stream's worker from the trajectory view its
session published last (no lock of the session's taken)."""

from __future__ import annotations

import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import Array, Trajectory
from occvo_schemas.pose_v1 import as_v1
from occvo_services.wire import encoding


class Queries:
    """The registration worker's queryables over its sessions."""

    def __init__(self, worker):
        self.worker = worker

    def _matching(self, query: zenoh.Query, key_of) -> list:
        q = query.key_expr
        views = ((stream, s.view) for stream, s in sorted(self.worker.sessions_now(), key=lambda i: i[0]))
        found = [
            (stream, view)
            for stream, view in views
            if view is not None and q.intersects(zenoh.KeyExpr(key_of(stream))) and self.worker.answers(stream)
        ]
        return found[: self.worker.config.max_query_streams]  # a wildcard asks for every stream: the first ones answer

    def _miss(self, query: zenoh.Query, what: str) -> None:
        """One worker answers a miss: the stream's (shard 0's for a wildcard)."""
        stream = keys.stream_of(str(query.key_expr))
        if self.worker.owns(stream):
            self.worker.reply_error(query, stream, "bad_query", f"no {what} for {query.key_expr}")

    def on_pose_latest(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.pose_latest)
        if not found:
            return self._miss(query, "poses")
        for stream, view in found:
            latest = view.latest
            if query.parameters.get("version") != "2":  # a client built before version 2 asks without it
                latest, version = as_v1(latest), 1
            else:
                version = 2
            query.reply(keys.pose_latest(stream), encode(latest), encoding=encoding("pose_estimate", version))

    def on_trajectory(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.trajectory)
        if not found:
            return self._miss(query, "trajectory")
        for stream, view in found:
            traj = Trajectory(
                stream=stream,
                seqs=Array.from_numpy(view.seqs),
                stamps=Array.from_numpy(view.stamps),
                poses=Array.from_numpy(view.poses),
            )
            query.reply(keys.trajectory(stream), encode(traj, 1 << 30), encoding=encoding("trajectory"))
