"""Registration worker: occupancy frames in, OccVO per stream, poses out in sequence order, map tile updates out.

Map updates: after each frame the worker tiles `vo.map_points()` (occvo_core.map_tiles) and publishes only the tiles
whose content changed (a tile that emptied is sent empty), so the map service always equals the odometry's map.
This costs one tiling of the map per frame (~tens of ms for 10^5 voxels) and keeps messages to the changed area.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import zenoh

from occvo_core.errors import InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.map_tiles import changed_tiles, tiles_from_map
from schemas import keys
from schemas.codec import encode
from schemas.models import Array, MapTile, MapUpdate, OccupancyFrameMsg, PoseEstimate, Trajectory
from services.runtime import Worker, WorkerConfig, log_event, worker_main

_STATUS = {"ok": "ok", "lost": "lost", "initialised": "reinitialised", "reinitialised": "reinitialised"}


class StreamState:
    def __init__(self, vo):
        self.vo = vo
        self.lock = threading.Lock()
        self.seqs: list[int] = []
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.latest: PoseEstimate | None = None
        self.tiles: dict = {}
        self.started = False


class RegistrationWorker(Worker):
    """Occupancy frames -> OccVO poses and map tiles."""

    role = "registration"

    def __init__(self, config: WorkerConfig):
        super().__init__(config)
        from occvo_core import OccVO, OccVOConfig

        self._OccVO = OccVO
        self.occvo_config = OccVOConfig.load(config.occvo_config) if config.occvo_config else OccVOConfig()
        self.states: dict[str, StreamState] = {}
        self._states_lock = threading.Lock()

    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.occupancy("*"), self._on_occupancy),
            s.declare_queryable(keys.pose_latest("*"), self._on_pose_latest),
            s.declare_queryable(keys.trajectory("*"), self._on_trajectory),
        ]

    def state(self, stream: str) -> StreamState:
        with self._states_lock:
            if stream not in self.states:
                self.states[stream] = StreamState(self._OccVO(self.occvo_config))
            return self.states[stream]

    def _on_occupancy(self, sample: zenoh.Sample) -> None:
        self.enqueue(sample, OccupancyFrameMsg, self._register)

    def _register(self, stream: str, item) -> None:
        msg, hop_ms, t_queued = item
        t0 = time.perf_counter()
        st = self.state(stream)
        frame = OccupancyFrame(msg.occupancy.to_points(), msg.occupancy.labels.to_numpy().copy(), index=msg.seq, stamp=msg.stamp,
                               meta={"stream": stream, "source": msg.source})
        try:
            frame.validate()  # before any reset, so a bad first frame leaves the old trajectory and map intact
            restart = msg.seq == 0 or not st.started
            if restart:  # only this lane's thread touches st.vo; queries read the lists below under st.lock
                st.vo.reset()
            result = st.vo.step(frame)
        except InvalidFrameError as exc:
            self.report_error(stream, "invalid_frame", f"seq {msg.seq}: {exc.reason}", keys.occupancy(stream), msg.seq)
            return
        reg_ms = (time.perf_counter() - t0) * 1000.0
        t_map = time.perf_counter()
        pts, labels = st.vo.map_points()
        tiles = tiles_from_map(pts, labels, self.config.tile_m)
        changed = tiles if restart else changed_tiles(st.tiles, tiles)
        update = MapUpdate(stream=stream, seq=msg.seq, reset=restart, tile_m=self.config.tile_m, tiles=[
            MapTile(stream=stream, ix=ix, iy=iy, tile_m=self.config.tile_m, seq=msg.seq,
                    points=Array.from_numpy(np.asarray(p, np.float64)), labels=Array.from_numpy(np.asarray(l, np.uint8)))
            for (ix, iy), (p, l) in sorted(changed.items())])
        self.session.put(keys.map_updates(stream), encode(update, 1 << 30), congestion_control=zenoh.CongestionControl.BLOCK)
        map_ms = (time.perf_counter() - t_map) * 1000.0
        timings = dict(msg.timings_ms)
        timings.update({"occupancy_hop": hop_ms, "registration_queue": (t0 - t_queued) * 1000.0, "registration": reg_ms,
                        "map_update": map_ms})
        timings.update({f"registration.{k}": float(v) for k, v in result.timings_ms.items()})
        pose = PoseEstimate(stream=stream, seq=msg.seq, stamp=msg.stamp, pose=np.asarray(result.pose, float).tolist(),
                            status=_STATUS.get(result.status, "ok"), timings_ms=timings, sent_at=time.time())
        with st.lock:
            if restart:
                st.seqs, st.stamps, st.poses = [], [], []
                st.started = True
            st.tiles = tiles
            st.seqs.append(msg.seq)
            st.stamps.append(msg.stamp)
            st.poses.append(np.asarray(result.pose, float))
            st.latest = pose
        self.session.put(keys.pose(stream), encode(pose), congestion_control=zenoh.CongestionControl.BLOCK)
        self.stats.inc("frames_out")
        self.stats.observe("registration", reg_ms)
        self.stats.observe("map_update", map_ms)
        self.stats.observe("occupancy_hop", hop_ms)
        self.stats.observe("stage_total", (time.perf_counter() - t0) * 1000.0)
        if restart:
            log_event(self.log, "trajectory started", stream=stream, seq=msg.seq)

    def _matching(self, query: zenoh.Query, key_of) -> list[tuple[str, StreamState]]:
        q = query.key_expr
        with self._states_lock:
            items = list(self.states.items())
        return [(s, st) for s, st in items if st.started and q.intersects(zenoh.KeyExpr(key_of(s)))]

    def _on_pose_latest(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.pose_latest)
        if not found:
            return self.reply_error(query, keys.stream_of(str(query.key_expr)), "bad_query", f"no poses for {query.key_expr}")
        for s, st in found:
            with st.lock:
                latest = st.latest
            query.reply(keys.pose_latest(s), encode(latest))

    def _on_trajectory(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.trajectory)
        if not found:
            return self.reply_error(query, keys.stream_of(str(query.key_expr)), "bad_query", f"no trajectory for {query.key_expr}")
        for s, st in found:
            with st.lock:
                traj = Trajectory(stream=s, seqs=Array.from_numpy(np.array(st.seqs, np.int64)),
                                  stamps=Array.from_numpy(np.array(st.stamps, np.float64)),
                                  poses=Array.from_numpy(np.array(st.poses, np.float64).reshape(-1, 4, 4)))
            query.reply(keys.trajectory(s), encode(traj, 1 << 30))


def _args(p) -> None:
    p.add_argument("--tile-m", type=float)
    p.add_argument("--occvo-config")


if __name__ == "__main__":
    sys.exit(worker_main(RegistrationWorker, extra_args=_args))
