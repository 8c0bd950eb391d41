"""OCC-VO: register each occupancy frame to the global semantic map, box by box as the paper's Fig. 2 draws it.

    preprocess -> initial guess -> local map (voxel pfilter) -> coarse GICP (semantic label filter)
    -> dynamic object filter -> fine GICP -> [loop closure] -> voxel pfilter map update

Each box is a module of occvo_core.registration; loop closure, the working map's paging and state save/load have
their own modules. OccVO holds the pipeline and its state between frames."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from occvo_core import state as state_io
from occvo_core import working_map
from occvo_core.config import OccVOConfig
from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame
from occvo_core.loop_closure import LoopClosure
from occvo_core.registration.dynamic_object_filter import find_moved_objects
from occvo_core.registration.ego_buffers import EgoBuffers
from occvo_core.registration.gicp import coarse_gicp, fine_gicp
from occvo_core.registration.initial_guess import initial_guess
from occvo_core.registration.kernels import use_threads
from occvo_core.registration.kernels.covariance import rotate_covariances, scatter
from occvo_core.registration.local_map import EgoMap, LocalMap, frame_window, transform, window_margin
from occvo_core.registration.pose_covariance import pose_covariance
from occvo_core.registration.preprocess import Prepared, preprocess
from occvo_core.registration.voxel_map import VoxelPFilterMap


def degenerate(points: np.ndarray) -> bool:
    """Fewer than three voxels, or all of them on one line (one voxel repeated, an all-zero coordinate table):
    registration cannot fix the pose, the frame is "degenerate"."""
    if len(points) < 3:
        return True
    quick = np.linalg.eigvalsh(scatter(points))
    if quick[1] > 1e-6 * quick[2]:  # a thousand times the threshold: rounding cannot carry it across
        return False
    centred = points - points.mean(axis=0)  # near the line: the test as it always was, bit for bit
    spread = np.linalg.eigvalsh(centred.T @ centred)  # ascending
    return bool(spread[1] <= 1e-9 * max(spread[2], 1e-300))


@dataclass
class StepResult:
    index: int
    pose: np.ndarray  # 4x4 ego -> world; the first frame defines the world
    status: str  # "initialised" for the first frame, then "ok" ("degenerate": a constant-velocity guess)
    timings_ms: dict[str, float] = field(default_factory=dict)
    pairs: dict[str, int] = field(default_factory=dict)
    loop_correction: np.ndarray | None = None  # 4x4 world -> world when this frame closed a loop (see LoopClosure)
    # 6x6 (rotation, translation) in base_link, from fine GICP's information (registration/pose_covariance.py); zeros
    # for the first frame (it defines the world), None where registration did not fix the pose
    covariance: np.ndarray | None = None


@dataclass
class _Pending:
    """What register() leaves for complete(): the frame and what fine GICP found around it."""

    frame: Prepared
    t: int
    watch: Stopwatch
    version: int
    local: LocalMap | None = None
    old: np.ndarray | None = None  # loop closure's old map in the window
    map_moved: np.ndarray | None = None  # the window's voxels of moved objects
    entered: tuple | None = None  # VoxelPFilterMap.enter()'s record of the window


@dataclass
class Registration:
    """OccVO.register()'s result: the frame's odometry pose before loop closure and the map update, which
    OccVO.complete() then makes."""

    index: int
    pose: np.ndarray  # 4x4 ego -> world, as registered against the map (a loop closed in complete() may move it)
    status: str
    pairs: dict[str, int] = field(default_factory=dict)
    covariance: np.ndarray | None = None  # as StepResult.covariance
    _pending: _Pending | None = field(default=None, repr=False)

    @property
    def timings_ms(self) -> dict[str, float]:
        return dict(self._pending.watch.ms)


class Stopwatch:
    """Milliseconds per stage of a frame. clock: wall time; a benchmark on a busy host may set the calling thread's
    CPU time (time.thread_time), which other processes disturb less (all of a stage's at threads=1)."""

    clock = staticmethod(time.perf_counter)

    def __init__(self):
        self.ms: dict[str, float] = {}
        self._t = self.clock()

    def restart(self) -> None:
        self._t = self.clock()

    def lap(self, stage: str) -> None:
        now = self.clock()
        self.ms[stage] = (now - self._t) * 1e3
        self._t = now


class OccVO:
    def __init__(self, config: OccVOConfig | None = None, *, threads: int = 0):
        """threads: cores the kernels of step() may use, 0 = all. Poses and map are the same for any value, so it
        is a run setting, not part of the config a saved state must match."""
        if threads < 0:
            raise ConfigError(f"threads must be >= 0 (0 = all cores), got {threads}")
        self.config = config or OccVOConfig()
        self.threads = threads
        self._margin = window_margin(self.config.voxel_pfilter.window_margin_m)
        self._ego_buffers = EgoBuffers()
        self.reset()

    def reset(self) -> None:
        self._version = getattr(self, "_version", 0) + 1  # any change: a pending Registration is stale (complete())
        pf = self.config.voxel_pfilter
        self.map = VoxelPFilterMap(
            pf.map_voxel_m,
            pf.p_index_threshold,
            pfilter=pf.enabled,
            merge_radius_m=pf.merge_radius_m,
            observe_radius_m=pf.observe_radius_m,
        )
        self.loop_closure = LoopClosure(self.config, self.map)
        self._poses: list[np.ndarray] = []
        self._indices: list[int] = []
        self._last: Prepared | None = None

    def _resume(self, poses: list[np.ndarray], indices: list[int], last: Prepared | None) -> None:
        """The pipeline's state as a saved run left it (occvo_core.state)."""
        self._poses, self._indices, self._last = poses, indices, last

    @property
    def loop_closures(self) -> list[tuple[int, np.ndarray]]:
        """(frame, 4x4 world -> world correction) of each loop closed: the map made since the place was last seen
        was moved by it, and poses from that frame on are relocalised (earlier poses stay as published)."""
        return [(t, c.copy()) for t, c in self.loop_closure.loops]

    @property
    def poses(self) -> np.ndarray:
        return np.array(self._poses).reshape(-1, 4, 4)

    @property
    def frame_indices(self) -> list[int]:
        return list(self._indices)

    def map_points(self, tiles: tuple[np.ndarray, np.ndarray, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The map (points, labels); with tiles = (lo, hi, tile_m), only the part in x-y tiles lo..hi."""
        return self.map.points(tiles)

    def pop_changed_region(self) -> np.ndarray | None:
        """x-y box of the map changed since the last call (see VoxelPFilterMap.pop_changed_region)."""
        return self.map.pop_changed_region()

    # -- state and the working map (occvo_core.state, occvo_core.working_map) ------------------------------------
    def state_dict(self, copy: bool = True) -> dict[str, np.ndarray]:
        """Everything needed to resume (see occvo_core.state); copy=False: views of the map arrays."""
        return state_io.state_dict(self, copy)

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Resume from state_dict(); the next step() continues bit for bit as if the run had never stopped."""
        state_io.load_state_dict(self, state)

    def evict_tiles(self, center_xy, radius_m: float, tile_m: float) -> dict[tuple[int, int], dict[str, np.ndarray]]:
        """Take the tiles wholly farther than radius_m from center_xy out of the map (see working_map)."""
        blocks = working_map.evict_tiles(self, center_xy, radius_m, tile_m)
        if blocks:
            self._version += 1
        return blocks

    def restore_tiles(self, blocks: dict[tuple[int, int], dict[str, np.ndarray]]) -> int:
        """Put evicted tiles back, moved by the loops closed since (see working_map); returns the voxels restored."""
        self._version += 1
        return working_map.restore_tiles(self, blocks)

    def resident_tiles(self, tile_m: float) -> set[tuple[int, int]]:
        """Tiles with voxels in the working map."""
        return self.map.resident_tiles(tile_m)

    # -- the pipeline --------------------------------------------------------------------------------------------
    def step(self, frame: OccupancyFrame) -> StepResult:
        """Register one frame. A bad frame raises InvalidFrameError and leaves poses and map as they were."""
        return self.complete(self.register(frame))

    def register(self, frame: OccupancyFrame) -> Registration:
        """The first half of step(): the frame's odometry pose, through fine GICP. Nothing changes until complete()
        takes it, so a service can publish the pose before the loop-closure search and the map update."""
        watch = Stopwatch()
        use_threads(self.threads)
        prepared = preprocess(frame, self.config)
        watch.lap("preprocess")
        t = len(self._poses)
        if t == 0:
            pending = _Pending(prepared, t, watch, self._version)  # the first frame defines the world: no error
            return Registration(frame.index, np.eye(4), "initialised", covariance=np.zeros((6, 6)), _pending=pending)
        return self.register_frame(prepared, t, watch)

    def register_frame(self, frame: Prepared, t: int, watch: Stopwatch) -> Registration:
        """Fig. 2 through fine GICP; complete() goes on with loop closure and the voxel pfilter's map update."""
        if degenerate(frame.points):  # GICP has nothing to hold the pose across the missing directions
            p = self._poses
            pose = p[-1] @ np.linalg.inv(p[-2]) @ p[-1] if len(p) >= 2 else p[-1].copy()  # constant velocity
            return Registration(frame.index, pose, "degenerate", _pending=_Pending(frame, t, watch, self._version))
        cfg = self.config
        guess = self._initial_guess(frame)
        watch.lap("initial_guess")
        # the window of map the frame reaches; usable: the voxel pfilter's reliable voxels (p-index > threshold)
        local = frame_window(self.map, guess, t, self._margin)
        entered = self.map.enter(local, t)
        old = self.loop_closure.old_map(local, t)
        self.loop_closure.follow(local, old)
        ego = EgoMap.around(local, guess, self._margin, buffers=self._ego_buffers)  # valid until the next frame's
        watch.lap("local_map")
        coarse = coarse_gicp(frame, ego, cfg)  # the semantic label filter drops pairs whose labels differ
        watch.lap("coarse_gicp")
        keep, map_moved, dynamic = find_moved_objects(frame, guess @ coarse.pose, local, cfg.dynamic_object_filter)
        watch.lap("dynamic_object_filter")
        ego.usable &= ~map_moved[ego.source]
        fine = fine_gicp(frame, frame.fine[keep[frame.fine]], ego, coarse.pose, cfg)
        pose = guess @ fine.pose
        watch.lap("fine_gicp")
        pairs = {
            "coarse_found": coarse.pairs_found,
            "coarse_semantic_kept": coarse.pairs_kept,
            "fine_found": fine.pairs_found,
            "fine_semantic_kept": fine.pairs_kept,
            **dynamic,
        }
        pending = _Pending(frame, t, watch, self._version, local, old, map_moved, entered)
        covariance = pose_covariance(fine.information, fine.pose)
        return Registration(frame.index, pose, "ok", pairs, covariance, _pending=pending)

    def complete(self, reg: Registration) -> StepResult:
        """The second half of step(): loop closure, then the voxel pfilter's map update. The pose is reg.pose, or the
        relocalised one when a loop closes (StepResult.loop_correction)."""
        p = reg._pending
        if p is None or p.version != self._version:
            raise RuntimeError(
                "complete() takes the registration of the frame just registered, before any other "
                "change to the odometry (step, complete, evict_tiles, restore_tiles, reset, load)"
            )
        p.watch.restart()  # the time between the halves (a service publishing the pose) is no stage's
        use_threads(self.threads)  # a service may run it in another thread than register()
        if reg.status == "degenerate":  # no loop search; the last frame stays the motion search's reference
            last = self._last
            self._commit(p.frame, reg.pose, np.zeros(0, np.int64))
            self._last = last
            p.watch.lap("voxel_pfilter")
            return StepResult(p.frame.index, reg.pose, "degenerate", p.watch.ms, {"map_voxels": len(self.map)})
        if p.t == 0:
            self._commit(p.frame, np.eye(4), np.zeros(0, np.int64))
            p.watch.lap("voxel_pfilter")
            return StepResult(
                p.frame.index,
                np.eye(4),
                "initialised",
                p.watch.ms,
                {"map_voxels": len(self.map)},
                None,
                np.zeros((6, 6)),
            )
        correction, loop = self.loop_closure.search(p.frame, reg.pose, p.t, p.local, p.old)
        p.watch.lap("loop_closure")
        pose = reg.pose if correction is None else correction @ reg.pose
        self._commit(
            p.frame,
            pose,
            p.local.rows[p.map_moved],
            p.local,
            correction,
            searched="loop_searched" in loop,
            on_old_map=loop.get("loop_on_old", 0) == 1,
            entered=p.entered,
        )
        p.watch.lap("voxel_pfilter")
        pairs = {
            **reg.pairs,
            "reliable_voxels": int(np.count_nonzero(p.local.usable)),
            "map_voxels": len(self.map),
            **loop,
        }
        return StepResult(
            p.frame.index,
            pose,
            "ok",
            p.watch.ms,
            pairs,
            None if correction is None else correction.copy(),
            reg.covariance,
        )

    def _initial_guess(self, frame: Prepared) -> np.ndarray:
        t = len(self._poses)
        return initial_guess(
            self._poses,
            self._last,
            frame,
            self.config.initialisation,
            relocalised_by=self.loop_closure.correction_at(t - 1),
        )

    def _commit(
        self,
        frame: Prepared,
        pose: np.ndarray,
        moved_rows: np.ndarray,
        local: LocalMap | None = None,
        correction: np.ndarray | None = None,
        searched: bool = False,
        on_old_map: bool = False,
        entered: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """The only place state changes: drop moved objects from the map, record the registration window, let loop
        closure correct the map, merge the frame (as loop closure's old map allows: see VoxelPFilterMap.merge),
        append the pose."""
        t = len(self._poses)
        self._version += 1
        if len(moved_rows):
            self.map.remove(moved_rows)
        if entered is not None:
            self.map.entered(*entered, t)
        if self.loop_closure.before_merge(self._poses, pose, t, correction, searched, on_old_map):
            local = None  # the closure moved the map: the window's rows and grid are stale
        covs_world = rotate_covariances(frame.covs, np.ascontiguousarray(pose[:3, :3]))
        self.map.merge(
            transform(pose, frame.points),
            frame.labels,
            covs_world,
            t,
            local,
            self.loop_closure.old_born_before(t),
            on_old_map,
        )
        self.map.compact()
        self.loop_closure.after_merge(t, on_old_map)
        self._poses.append(pose)
        self._indices.append(frame.index)
        self._last = frame
