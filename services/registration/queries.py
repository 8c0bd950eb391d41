"""Queries: a stream's latest pose and its trajectory, answered from its session's memory by the stream's worker."""

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
        found = [
            (stream, s)
            for stream, s in sorted(self.worker.sessions_now(), key=lambda i: i[0])
            if s.trajectory.started and q.intersects(zenoh.KeyExpr(key_of(stream))) and self.worker.answers(stream)
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
        for stream, s in found:
            latest = s.trajectory.latest_pose()
            if query.parameters.get("version") != "2":  # a client built before version 2 asks without it
                latest, version = as_v1(latest), 1
            else:
                version = 2
            query.reply(keys.pose_latest(stream), encode(latest), encoding=encoding("pose_estimate", version))

    def on_trajectory(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.trajectory)
        if not found:
            return self._miss(query, "trajectory")
        for stream, s in found:
            seqs, stamps, poses = s.trajectory.arrays()
            traj = Trajectory(
                stream=stream,
                seqs=Array.from_numpy(seqs),
                stamps=Array.from_numpy(stamps),
                poses=Array.from_numpy(poses),
            )
            query.reply(keys.trajectory(stream), encode(traj, 1 << 30), encoding=encoding("trajectory"))
