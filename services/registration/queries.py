"""Queries: a stream's latest pose and its trajectory, answered from memory by the stream's shard."""

from __future__ import annotations

import time

import numpy as np
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import Array, PoseEstimate, Trajectory
from occvo_services.registration.state import StreamState
from occvo_services.store import StoredPose


class Queries:
    """RegistrationWorker's queryables."""

    @staticmethod
    def _pose_msg(stream: str, p: StoredPose) -> PoseEstimate:
        return PoseEstimate(
            stream=stream,
            seq=p.seq,
            stamp=p.stamp,
            pose=np.asarray(p.pose, float).tolist(),
            status=p.status,
            timings_ms={},
            sent_at=time.time(),
        )

    def _matching(self, query: zenoh.Query, key_of) -> list[tuple[str, StreamState]]:
        q = query.key_expr
        with self._states_lock:
            items = list(self.states.items())
        found = [
            (s, st)
            for s, st in sorted(items, key=lambda i: i[0])
            if st.started and q.intersects(zenoh.KeyExpr(key_of(s)))
        ]
        return found[: self.config.max_query_streams]  # a wildcard asks for every stream: the first ones answer

    def _on_pose_latest(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.pose_latest)
        if not found:  # one worker answers a miss: the stream's shard's (shard 0's for a wildcard)
            if self.owns(keys.stream_of(str(query.key_expr))):
                self.reply_error(
                    query, keys.stream_of(str(query.key_expr)), "bad_query", f"no poses for {query.key_expr}"
                )
            return
        for s, st in found:
            with st.lock:
                latest = st.latest
            query.reply(keys.pose_latest(s), encode(latest))

    def _on_trajectory(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.trajectory)
        if not found:  # one worker answers a miss: the stream's shard's (shard 0's for a wildcard)
            if self.owns(keys.stream_of(str(query.key_expr))):
                self.reply_error(
                    query, keys.stream_of(str(query.key_expr)), "bad_query", f"no trajectory for {query.key_expr}"
                )
            return
        for s, st in found:
            with st.lock:
                traj = Trajectory(
                    stream=s,
                    seqs=Array.from_numpy(np.array(st.seqs, np.int64)),
                    stamps=Array.from_numpy(np.array(st.stamps, np.float64)),
                    poses=Array.from_numpy(np.array(st.poses, np.float64).reshape(-1, 4, 4)),
                )
            query.reply(keys.trajectory(s), encode(traj, 1 << 30))
