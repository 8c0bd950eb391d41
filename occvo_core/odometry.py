"""OCC-VO: register each occupancy frame to the global semantic map (the paper's Fig. 2, one method per box)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.config import OccVOConfig
from occvo_core.errors import ConfigError, InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import GROUND_CLASSES, MOVABLE_CLASSES, OCC3D_GRID
from occvo_core.map_tiles import pack_tiles
from occvo_core.registration import kernels
from occvo_core.registration.dynamic_object_filter import dynamic_object_filter
from occvo_core.registration.gicp import gicp, rotation_angle
from occvo_core.registration.initialisation import bev_first_motion, ground_height_correction, semantic_bev_motion
from occvo_core.registration.voxel_map import EgoMap, VoxelPFilterMap, _field, moved

_GRID_CORNERS = np.array(np.meshgrid(*zip(OCC3D_GRID.lower, OCC3D_GRID.upper), indexing="ij")).reshape(3, -1).T
_EGO_LOWER, _EGO_UPPER = np.array(OCC3D_GRID.lower), np.array(OCC3D_GRID.upper)


@dataclass
class StepResult:
    index: int
    pose: np.ndarray  # 4x4 ego -> world; the first frame defines the world
    status: str  # "initialised" for the first frame, then "ok"
    timings_ms: dict[str, float] = field(default_factory=dict)
    pairs: dict[str, int] = field(default_factory=dict)
    loop_correction: np.ndarray | None = None  # 4x4 world -> world when this frame closed a loop (see _loop_closure)


@dataclass
class Registration:
    """OccVO.register()'s result: the frame's odometry pose before loop closure and the map update, which
    OccVO.complete() then makes from the rest (private: what fine GICP left for them)."""

    index: int
    pose: np.ndarray  # 4x4 ego -> world, as registered against the map (a loop closed in complete() may move it)
    status: str
    pairs: dict[str, int] = field(default_factory=dict)
    _frame: "_Prepared | None" = field(default=None, repr=False)
    _t: int = 0
    _watch: "_Stopwatch | None" = field(default=None, repr=False)
    _version: int = 0
    _local: object = field(default=None, repr=False)
    _old: np.ndarray | None = field(default=None, repr=False)
    _map_moved: np.ndarray | None = field(default=None, repr=False)
    _entered: tuple | None = field(default=None, repr=False)

    @property
    def timings_ms(self) -> dict[str, float]:
        return dict(self._watch.ms)


@dataclass
class _Prepared:
    """A frame made ready for registration: per-point GICP covariances and two downsampled source sets."""

    points: np.ndarray
    labels: np.ndarray
    covs: np.ndarray
    wide: np.ndarray  # indices of the wide-pass sources
    coarse: np.ndarray  # indices of the coarse-GICP sources
    fine: np.ndarray  # indices of the fine-GICP sources
    movable: np.ndarray  # indices of movable-class points
    index: int = 0


class _Stopwatch:
    def __init__(self):
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def restart(self) -> None:
        self._t = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.ms[stage] = (now - self._t) * 1e3
        self._t = now


def _block_factor(voxel_m: float) -> int:
    """Grid voxels per side of a downsampling block of voxel_m."""
    return max(1, int(round(voxel_m / OCC3D_GRID.voxel_size)))


def _transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


class OccVO:
    def __init__(self, config: OccVOConfig | None = None, *, threads: int = 0):
        """threads: cores the kernels of step() may use, 0 = all. Poses and map are the same for any value, so it
        is a run setting, not part of the config a saved state must match."""
        if threads < 0:
            raise ConfigError(f"threads must be >= 0 (0 = all cores), got {threads}")
        self.config = config or OccVOConfig()
        self.threads = threads
        self.reset()

    @property
    def _margin(self) -> np.ndarray:
        m = self.config.voxel_pfilter.window_margin_m
        return np.array([m, m, min(m, 1.0)])  # the ground does not move 4 m up between frames

    def reset(self) -> None:
        self._version = getattr(self, "_version", 0) + 1  # any change: a pending Registration is stale (complete())
        pf = self.config.voxel_pfilter
        self.map = VoxelPFilterMap(pf.map_voxel_m, pf.p_index_threshold, pfilter=pf.enabled, merge_radius_m=pf.merge_radius_m,
                                   observe_radius_m=pf.observe_radius_m)
        self._poses: list[np.ndarray] = []
        self._indices: list[int] = []
        self._last: _Prepared | None = None
        self._loops: list[tuple[int, np.ndarray]] = []  # (frame, correction) of every loop closed
        self._last_loop_search = -(1 << 30)  # frame of the last loop search
        self._on_old_map = False  # the last frame lay on the old map (loop closure's lock_share)
        self._anchor = 0  # the last frame on the old map (or the first): the map since then drifted with the poses
        self._followed_buf = np.zeros(256, bool)  # per frame: it followed the old map (its new voxels are recent map only)
        # per loop closed: the frames (anchor, t] and the world -> world correction of the map made at each
        self._map_corrections: list[tuple[int, np.ndarray, np.ndarray]] = []

    @property
    def _followed(self) -> np.ndarray:
        return self._followed_buf[: len(self._poses)]

    @property
    def loop_closures(self) -> list[tuple[int, np.ndarray]]:
        """(frame, 4x4 world -> world correction) of each loop closed: the map made since the place was last seen
        was moved by it, and poses from that frame on are relocalised (earlier poses stay as published)."""
        return [(t, c.copy()) for t, c in self._loops]

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

    # -- state for durable storage and paging (the store itself lives outside occvo_core) ------------------------
    def state_dict(self, copy: bool = True) -> dict[str, np.ndarray]:
        """Everything needed to resume: config, poses, frame indices, the voxel pfilter map and the last frame.
        copy=False gives views of the map arrays, for a caller that writes them out before the next step."""
        out = {"config_json": np.frombuffer(self.config.model_dump_json().encode(), np.uint8),
               "poses": self.poses, "indices": np.array(self._indices, np.int64)}
        out.update({f"map.{k}": v for k, v in self.map.state(copy).items()})
        out["loops"] = np.array([[t, *c.ravel()] for t, c in self._loops], np.float64).reshape(-1, 17)
        out["last_loop_search"] = np.array(self._last_loop_search, np.int64)
        out["on_old_map"] = np.array(self._on_old_map)
        out["anchor"] = np.array(self._anchor, np.int64)
        out["followed_frames"] = np.flatnonzero(self._followed).astype(np.int64)
        out["map_corrections"] = np.array([[t, b, *c.ravel()] for t, frames, cs in self._map_corrections
                                           for b, c in zip(frames, cs)], np.float64).reshape(-1, 18)
        if self._last is not None:
            out.update({f"last.{k}": np.asarray(v) for k, v in vars(self._last).items()})
        return out

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Resume from state_dict(); the next step() continues bit for bit as if the run had never stopped."""
        saved = bytes(np.asarray(state["config_json"], np.uint8)).decode()
        try:  # compared as configs, not text: a section added since takes its default
            same = OccVOConfig.model_validate_json(saved) == self.config
        except ValueError:
            same = False
        if not same:
            raise ConfigError("saved odometry state was made with another OccVOConfig; refusing to mix them "
                              f"(saved: {saved})")
        self.reset()
        self.map.load_state({k[4:]: np.asarray(v) for k, v in state.items() if k.startswith("map.")})
        self._poses = [np.array(p, np.float64) for p in np.asarray(state["poses"]).reshape(-1, 4, 4)]
        self._indices = [int(i) for i in state["indices"]]
        self._loops = [(int(row[0]), row[1:].reshape(4, 4).copy()) for row in np.asarray(state.get("loops", np.zeros((0, 17))))]
        self._last_loop_search = int(state.get("last_loop_search", self._last_loop_search))
        self._on_old_map = bool(state.get("on_old_map", False))
        self._anchor = int(state.get("anchor", 0))
        self._followed_buf = np.zeros(max(256, 2 * len(self._poses)), bool)
        self._followed_buf[np.asarray(state.get("followed_frames", np.zeros(0, np.int64)), np.int64)] = True
        rows = np.asarray(state.get("map_corrections", np.zeros((0, 18))))
        for t in np.unique(rows[:, 0]).astype(np.int64):
            mine = rows[rows[:, 0] == t]
            self._map_corrections.append((int(t), mine[:, 1].astype(np.int64), mine[:, 2:].reshape(-1, 4, 4).copy()))
        if "last.points" in state:
            last = {k[5:]: np.asarray(v) for k, v in state.items() if k.startswith("last.")}
            last["index"] = int(last["index"])
            self._last = _Prepared(**last)

    def evict_tiles(self, center_xy, radius_m: float, tile_m: float) -> dict[tuple[int, int], dict[str, np.ndarray]]:
        """Take out of the working map every tile (ix, iy) = floor(xy / tile_m) whose square lies wholly farther
        than radius_m from center_xy; returns {tile: voxels} for the caller to keep (bounded memory on long drives)."""
        center = np.asarray(center_xy, np.float64)
        rows = kernels.far_tile_rows(self.map.pos, self.map.alive, self.map._n, center[0], center[1], float(tile_m),
                                     float(radius_m))
        if len(rows) == 0:
            return {}
        self._version += 1
        t = len(self._poses)
        tiles = np.floor(self.map.pos[rows, :2] / tile_m).astype(np.int64)
        _, first, inverse = np.unique(pack_tiles(tiles), return_index=True, return_inverse=True)
        uniq = tiles[first]
        inverse = inverse.reshape(-1)
        order = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
        out = {(int(uniq[u, 0]), int(uniq[u, 1])): self.map.take(rows[order[bounds[u]:bounds[u + 1]]], t)
               for u in range(len(uniq))}
        self.map.compact()
        return out

    def restore_tiles(self, blocks: dict[tuple[int, int], dict[str, np.ndarray]]) -> int:
        """Put evicted tiles back (as evict_tiles returned them), moved by the loops closed since they were taken;
        returns the voxels restored."""
        t = len(self._poses)
        self._version += 1
        restored = sum(self.map.put(self._corrected_block(block), t) for block in blocks.values())
        self._drop_followed_voxels(t - 1, restored=True)  # taken before they came of age: as if never taken
        return restored

    def _corrected_block(self, block: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """An evicted block as the loops closed since it was taken would have moved it (see _correct_map)."""
        taken = int(block["taken_at"])
        later = [c for c in self._map_corrections if c[0] >= taken]
        if not later or len(block["keys"]) == 0:
            return block
        block = dict(block)
        born = _field(block, "born").astype(np.int64)
        pos, cov = np.array(block["pos"], np.float64), np.array(block["cov"], np.float64)
        for _, frames, corrections in later:
            k = np.searchsorted(frames, born)
            mine = np.flatnonzero((k < len(frames)) & (frames[np.minimum(k, len(frames) - 1)] == born))
            pos[mine], cov[mine] = moved(pos[mine], cov[mine], corrections[:, :3, :3], corrections[:, :3, 3], k[mine])
        block.update(pos=pos, cov=cov, keys=np.floor(pos / self.map.voxel).astype(np.int64))
        return block

    def resident_tiles(self, tile_m: float) -> set[tuple[int, int]]:
        """Tiles with voxels in the working map."""
        n = self.map._n
        tiles = self.map.tile_ids(tile_m)[self.map.alive[:n]]
        if not len(tiles):
            return set()
        _, first = np.unique(pack_tiles(tiles), return_index=True)
        return {(int(a), int(b)) for a, b in tiles[first]}

    def step(self, frame: OccupancyFrame) -> StepResult:
        """Register one frame. A bad frame raises InvalidFrameError and leaves poses and map as they were."""
        return self.complete(self.register(frame))

    def register(self, frame: OccupancyFrame) -> Registration:
        """The first half of step(): the frame's odometry pose, through fine GICP. Nothing changes until complete()
        takes it, so a service can publish the pose before the loop-closure search and the map update."""
        watch = _Stopwatch()
        kernels.use_threads(self.threads)
        prepared = self._preprocess(frame)
        watch.lap("preprocess")
        t = len(self._poses)
        if t == 0:
            return Registration(frame.index, np.eye(4), "initialised", _frame=prepared, _t=t, _watch=watch,
                                _version=self._version)
        return self.register_frame(prepared, t, watch)

    def complete(self, reg: Registration) -> StepResult:
        """The second half of step(): loop closure, then the voxel pfilter's map update. The pose is reg.pose, or the
        relocalised one when a loop closes (StepResult.loop_correction)."""
        if reg._version != self._version:
            raise RuntimeError("complete() takes the registration of the frame just registered, before any other "
                               "change to the odometry (step, complete, evict_tiles, restore_tiles, reset, load)")
        frame, t, watch = reg._frame, reg._t, reg._watch
        watch.restart()  # the time between the halves (a service publishing the pose) is no stage's
        if t == 0:
            self._commit(frame, np.eye(4), np.zeros(0, np.int64))
            watch.lap("voxel_pfilter")
            return StepResult(frame.index, np.eye(4), "initialised", watch.ms, {"map_voxels": len(self.map)})
        pose, local = reg.pose, reg._local
        correction, loop = self._loop_closure(frame, pose, t, local, reg._old)
        watch.lap("loop_closure")
        if correction is not None:
            pose = correction @ pose
        self._commit(frame, pose, local.rows[reg._map_moved], local, correction, searched="loop_searched" in loop,
                     on_old_map=loop.get("loop_on_old", 0) == 1, entered=reg._entered)
        watch.lap("voxel_pfilter")
        pairs = {**reg.pairs, "reliable_voxels": int(local.usable.sum()), "map_voxels": len(self.map), **loop}
        return StepResult(frame.index, pose, "ok", watch.ms, pairs, None if correction is None else correction.copy())

    def register_frame(self, frame: _Prepared, t: int, watch: _Stopwatch) -> Registration:
        """Coarse GICP -> semantic label filter -> dynamic object filter -> fine GICP; complete() goes on with
        (loop closure) -> voxel pfilter."""
        cfg = self.config.gicp
        guess = self._initial_guess(frame)
        watch.lap("initial_guess")
        local = self._local_map(guess, t)  # local.usable: the voxel pfilter's reliable voxels (p-index > threshold)
        entered = self.map.enter(local, t)
        old = self._old_map(local, t)
        if self._on_old_map:  # following a place mapped long ago: its map constrains registration again
            local.usable |= old
        ego = EgoMap.build(local, guess, _EGO_LOWER - self._margin, _EGO_UPPER + self._margin, self.map.voxel)
        watch.lap("local_map")
        coarse = self._coarse_gicp(frame, ego)
        watch.lap("coarse_gicp")
        keep, map_moved, dyn = self._dynamic_object_filter(frame, guess @ coarse.pose, local)
        watch.lap("dynamic_object_filter")
        ego.usable &= ~map_moved[ego.source]
        fine = self._gicp(frame, frame.fine[keep[frame.fine]], ego, coarse.pose, cfg.fine_max_correspondence_m,
                          cfg.fine_iterations)
        pose = guess @ fine.pose
        watch.lap("fine_gicp")
        pairs = {"coarse_found": coarse.pairs_found, "coarse_semantic_kept": coarse.pairs_kept,
                 "fine_found": fine.pairs_found, "fine_semantic_kept": fine.pairs_kept, **dyn}
        return Registration(frame.index, pose, "ok", pairs, _frame=frame, _t=t, _watch=watch, _version=self._version,
                            _local=local, _old=old, _map_moved=map_moved, _entered=entered)

    # -- the boxes of the pipeline ------------------------------------------------------------------------------
    def _preprocess(self, frame: OccupancyFrame) -> _Prepared:
        frame.validate()
        points = np.ascontiguousarray(frame.points, dtype=np.float64)
        shape = np.array(OCC3D_GRID.shape, np.int64)
        ijk, outside = kernels.grid_indices(points, _EGO_LOWER, OCC3D_GRID.voxel_size, shape)
        if outside:
            raise InvalidFrameError(frame.index, f"{outside} points outside the occupancy grid "
                                    f"{OCC3D_GRID.lower}..{OCC3D_GRID.upper} (is the frame in ego coordinates?)")
        labels = np.asarray(frame.labels, np.uint8)
        # the same points in any order give the same pose and map: sources are the first voxel of each block in
        # grid order, i.e. the block's rear-most (lowest ego x), a choice that moves the along-track error (README)
        cell = (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]
        if len(cell) > 1 and not np.all(cell[1:] > cell[:-1]):
            order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], labels, cell))
            points, labels, ijk = points[order], labels[order], ijk[order]
        max_range = self.config.max_range_m
        if max_range is not None:  # camera occupancy is least sure of what is far
            near = points[:, 0] ** 2 + points[:, 1] ** 2 <= max_range ** 2
            points, labels, ijk = points[near], labels[near], ijk[near]
        surface, grid = kernels.surface_voxels(ijk, shape)
        if len(surface) < len(points):
            points, labels, ijk = points[surface], labels[surface], ijk[surface]
        g = self.config.gicp
        covs = kernels.plane_covariances(points, ijk, grid, shape, g.k_neighbours_radius_voxels, g.covariance_epsilon)
        wide, coarse, fine = kernels.thin_sources(
            ijk, np.isin(labels, GROUND_CLASSES), shape, _block_factor(g.wide_voxel_m) if g.wide_voxel_m > 0 else 0,
            _block_factor(g.coarse_source_voxel_m), _block_factor(g.source_voxel_m), _block_factor(g.ground_source_voxel_m),
            ("first", "balanced", "uniform").index(g.source_pick))
        return _Prepared(points, labels, covs, wide, coarse, fine, np.flatnonzero(np.isin(labels, MOVABLE_CLASSES)), frame.index)

    def _initial_guess(self, frame: _Prepared) -> np.ndarray:
        init = self.config.initialisation
        if len(self._poses) >= 2 and init.use_constant_velocity:
            before = self._poses[-2]
            if self._loops and self._loops[-1][0] == len(self._poses) - 1:
                before = self._loops[-1][1] @ before  # the last pose was relocalised: the motion is not the jump
            motion = np.linalg.inv(before) @ self._poses[-1]
            if init.motion_search:
                prev = self._last
                motion = semantic_bev_motion(prev.points, prev.labels, frame.points, frame.labels, guess=motion,
                                             search_radius_m=init.motion_search_radius_m,
                                             yaw_deg=init.motion_search_yaw_deg, step_deg=init.motion_search_step_deg,
                                             prior_sigma_m=init.motion_search_prior_m)
            return self._poses[-1] @ motion
        prev = self._last
        motion, _ = bev_first_motion(prev.points, prev.labels, frame.points, frame.labels,
                                     search_radius_m=init.bev_search_radius_m, yaw_steps_deg=init.bev_yaw_steps_deg)
        return self._poses[-1] @ motion

    def _local_map(self, pose: np.ndarray, t: int, margin: np.ndarray | None = None, tight: bool = False):
        """The map voxels the frame can reach from `pose`: its grid's box in the world, with a margin for the
        correction registration will make (tight: see VoxelPFilterMap.window)."""
        corners = _transform(pose, _GRID_CORNERS)
        margin = self._margin if margin is None else margin
        lower = np.floor((corners.min(axis=0) - margin) / self.map.voxel).astype(np.int64)
        upper = np.floor((corners.max(axis=0) + margin) / self.map.voxel).astype(np.int64)
        return self.map.window(lower, upper, t, tight)

    def _old_map(self, local, t: int) -> np.ndarray | None:
        """Mask of the window's voxels that are the old map for loop closure: made at least min_gap_frames ago,
        and reliable while they were in view (their p-index now also counts the frames since). None without
        loop closure or before min_gap_frames."""
        lc = self.config.loop_closure
        if not lc.enabled or t <= lc.min_gap_frames:
            return None
        return self.map.persistent_rows(local.rows, born_before=t - lc.min_gap_frames)

    def _coarse_gicp(self, frame: _Prepared, ego: EgoMap):
        """Coarse GICP against the map pooled on a coarse grid. A wide pass first (the map pooled wider still) reaches
        minima metres away; when it lands far from the guess, both starts are refined and the one whose alignment
        keeps clearly more pairs wins, since repeated structure (tree rows, lamp posts) can give the wide pass a wrong one."""
        cfg = self.config.gicp
        coarse_map = ego.pooled(cfg.coarse_map_voxel_m)
        starts = [np.eye(4)]
        if cfg.wide_voxel_m > 0:
            wide = self._gicp(frame, frame.wide, coarse_map.pooled(cfg.wide_voxel_m), np.eye(4), cfg.wide_voxel_m,
                              cfg.coarse_iterations).pose
            # a wide pass that barely moved the guess leads coarse GICP to the minimum the guess would; one that moved
            # it further may lead it on into a neighbouring one (scene-0101 turned 180 degrees, frame 18: 2.8 m off)
            near = np.linalg.norm(wide[:3, 3]) < cfg.wide_trust_m and \
                rotation_angle(wide[:3, :3]) < np.deg2rad(2.0)
            starts = [wide] if near else [np.eye(4), wide]
        results = [self._gicp(frame, frame.coarse, coarse_map, start, cfg.coarse_max_correspondence_m,
                              cfg.coarse_iterations) for start in starts]
        if len(results) == 1:
            return results[0]
        from_guess, from_wide = results
        # the guess is the prior: the wide pass's minimum must be clearly better supported to replace it
        return from_wide if from_wide.pairs_kept > (1 + cfg.wide_pairs_margin) * from_guess.pairs_kept else from_guess

    def _gicp(self, frame: _Prepared, idx: np.ndarray, local, pose: np.ndarray, max_dist: float, iterations: int):
        g = self.config.gicp
        return gicp(frame.points[idx], frame.covs[idx], frame.labels[idx], local, pose,
                    max_correspondence_m=max_dist, iterations=iterations, robust_scale=g.robust_kernel_scale,
                    semantic_label_filter=self.config.semantic_label_filter.enabled,
                    convergence_rotation_rad=g.convergence_rotation_rad, convergence_translation_m=g.convergence_translation_m,
                    correspondence_reuse=g.correspondence_reuse)

    def _dynamic_object_filter(self, frame: _Prepared, pose: np.ndarray, local):
        """Returns (mask of frame points kept for fine GICP, mask of local voxels of moved objects, counts)."""
        keep = np.ones(len(frame.points), bool)
        map_moved = np.zeros(len(local), bool)
        d = self.config.dynamic_object_filter
        if not d.enabled or len(frame.movable) == 0:
            return keep, map_moved, {"dynamic_frame_objects": 0, "dynamic_map_objects": 0, "dynamic_points": 0,
                                     "dynamic_map_voxels_removed": 0}
        movable_world = _transform(pose, frame.points[frame.movable])
        # map objects are judged only where this frame can see them: inside its grid, after the coarse alignment
        candidates = np.flatnonzero(np.isin(local.labels, MOVABLE_CLASSES))
        in_view = OCC3D_GRID.inside(OCC3D_GRID.indices_of(_transform(np.linalg.inv(pose), local.pos[candidates])))
        candidates = candidates[in_view]
        found = dynamic_object_filter(movable_world, local.pos[candidates], threshold_m=d.displacement_threshold_m,
                                      cluster_eps_m=d.cluster_eps_m, min_cluster_points=d.min_cluster_voxels,
                                      quantile=d.displacement_quantile)
        keep[frame.movable[found.frame_moved]] = False
        map_moved[candidates[found.map_moved]] = True
        return keep, map_moved, {"dynamic_frame_objects": found.frame_objects, "dynamic_map_objects": found.map_objects,
                                 "dynamic_points": int(found.frame_moved.sum()),
                                 "dynamic_map_voxels_removed": int(found.map_moved.sum())}

    def _loop_closure(self, frame: _Prepared, pose: np.ndarray, t: int, local,
                      old: np.ndarray | None) -> tuple[np.ndarray | None, dict[str, int]]:
        """Back at a place mapped long ago, with drift beyond GICP's reach: find the frame on that old map (a BEV
        correlation over metres, then coarse and fine GICP against the old voxels alone) and return the correction
        (world -> world) when it puts far more of the frame on the old map than the registered pose does.
        info["loop_on_old"] says whether the frame (relocalised or not) lies on the old map."""
        lc, g = self.config.loop_closure, self.config.gicp
        if old is None:
            return None, {}
        info = {"loop_old_voxels": int(old.sum())}
        if info["loop_old_voxels"] < lc.min_old_voxels:
            return None, info
        # the share is judged on static structure: ground lies on old ground at any offset along a road
        src = frame.fine[~np.isin(frame.labels[frame.fine], GROUND_CLASSES + MOVABLE_CLASSES)]
        share, covered = self._share_on(frame, src, pose, local, old)
        info["loop_share_pct"] = int(round(100 * share))
        info["loop_on_old"] = int(covered >= lc.min_overlap and share >= lc.lock_share)
        if share >= lc.lock_share or len(src) == 0 or t - self._last_loop_search < lc.search_every_frames:
            return None, info
        info["loop_searched"] = 1
        # what the recent map already explains at this pose is the road just driven: the rest of the frame is what
        # must be found on the old map (and the trail's rows of trees and houses would only alias the search)
        recent = local.map.alive[local.rows] & ~old
        d, _ = local.nearest(_transform(pose, frame.points), int(np.ceil(g.fine_max_correspondence_m / local.voxel)),
                             usable=recent)
        unexplained = d > g.fine_max_correspondence_m
        # search the old map as far around the frame as the search reaches, not just its registration window
        local = self._local_map(pose, t, self._margin + [lc.search_radius_m, lc.search_radius_m, lc.search_height_m],
                                tight=True)
        old = self._old_map(local, t)
        inverse = np.linalg.inv(pose)
        motion, _ = bev_first_motion(_transform(inverse, local.pos[old]), local.labels[old], frame.points[unexplained],
                                     frame.labels[unexplained], search_radius_m=lc.search_radius_m,
                                     yaw_steps_deg=lc.yaw_steps_deg)
        candidate = pose @ motion
        # height, roll and pitch drift too on a long drive: level the frame's ground on the old map's
        level = ground_height_correction(local.pos[old & np.isin(local.labels, GROUND_CLASSES)],
                                         _transform(candidate, frame.points[np.isin(frame.labels, GROUND_CLASSES)]),
                                         candidate[:3, 3])
        if level is not None:
            candidate = level @ candidate
        ego = EgoMap.build(local, candidate, _EGO_LOWER - self._margin, _EGO_UPPER + self._margin, self.map.voxel,
                           subset=old)
        coarse = self._coarse_gicp(frame, ego)  # with its wide pass: the BEV peak can be metres off along a street
        fine = self._gicp(frame, frame.fine, ego, coarse.pose, g.fine_max_correspondence_m, g.fine_iterations)
        relocalised = candidate @ fine.pose
        found, covered = self._share_on(frame, src, relocalised, local, old)
        jump = float(np.linalg.norm(relocalised[:3, 3] - pose[:3, 3]))
        on_covered = found / max(covered, 1e-9)
        info.update(loop_found_pct=int(round(100 * found)), loop_covered_pct=int(round(100 * covered)),
                    loop_jump_mm=int(round(1000 * jump)))
        # judged where the old map is: coming back, a frame still sees the road it came by, which the old map lacks
        if on_covered < lc.accept_share or covered < lc.min_overlap or found < 2 * share or jump < lc.min_correction_m:
            return None, info
        info["loop_closed"] = info["loop_on_old"] = 1
        return relocalised @ inverse, info

    def _correct_map(self, pose: np.ndarray, correction: np.ndarray, t: int) -> None:
        """Spread the loop correction over the map made since the anchor (the last frame on the old map), as a pose
        graph with equal weights along the path would: each frame's heading takes the rotation in proportion to
        the distance driven since the anchor, the path is integrated again with it, and what is left of the
        translation is spread the same way. Each voxel moves with the frame that made it, so the last frame gets
        the whole correction and the anchor none. Moved voxels that land on the anchor's map are dropped as ghosts
        of it (VoxelPFilterMap.move)."""
        lc = self.config.loop_closure
        a = self._anchor
        frames = np.arange(a + 1, t + 1)
        ego = np.array([p[:3, 3] for p in self._poses[a:]] + [pose[:3, 3]])  # frames a..t, registered
        step = np.diff(ego, axis=0)
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(step, axis=1))])
        share = travelled / max(travelled[-1], 1e-9)
        turn = Rotation.from_rotvec(share[:, None] * Rotation.from_matrix(correction[:3, :3]).as_rotvec())
        rot = turn.as_matrix()
        path = ego[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(np.einsum("nij,nj->ni", rot[1:], step), axis=0)])
        target = correction[:3, :3] @ ego[-1] + correction[:3, 3]
        path += share[:, None] * (target - path[-1])
        corrections = np.tile(np.eye(4), (len(frames), 1, 1))
        corrections[:, :3, :3] = rot[1:]
        corrections[:, :3, 3] = path[1:] - np.einsum("nij,nj->ni", rot[1:], ego[1:])
        self._map_corrections.append((t, frames, corrections))
        n = self.map._n
        rows = np.flatnonzero(self.map.alive[:n] & (self.map.born[:n] > a))
        self.map.move(rows, corrections[:, :3, :3], corrections[:, :3, 3], ghost_radius_m=lc.ghost_radius_m,
                      born_before=a + 1, group=self.map.born[rows] - a - 1)

    def _drop_followed_voxels(self, t: int, restored: bool = False) -> None:
        """Voxels made by frames that followed the old map are the recent map registration needs where that map is
        thin, never old map themselves: dropped before they would be (min_gap_frames old). A lap that slipped along a
        street of repeated structure made its copy of the place there, and as old map it pulled the next laps the
        same way (README, Reliability: seed 1's start, laps 13 and 14). Per frame only frame t - min_gap_frames comes
        of age (one scan, and only if it followed); tiles just restored may hold voxels of any earlier frame."""
        b = t - self.config.loop_closure.min_gap_frames
        if b < 0 or not (self._followed[: b + 1].any() if restored else self._followed[b]):
            return
        n = self.map._n
        born = self.map.born[:n]
        if restored:
            rows = np.flatnonzero(self.map.alive[:n] & (born <= b))
            rows = rows[self._followed[born[rows]]]
        else:
            rows = np.flatnonzero(self.map.alive[:n] & (born == b))
        if len(rows):
            self.map.remove(rows)

    def _share_on(self, frame: _Prepared, idx: np.ndarray, pose: np.ndarray, local, subset: np.ndarray) -> tuple[float, float]:
        """Shares of frame points idx that, at pose, have a voxel of subset with their label within the fine GICP
        correspondence distance, and that have one of any label within twice the coarse correspondence distance
        (the part of the frame the subset covers)."""
        if len(idx) == 0:
            return 0.0, 0.0
        reach = self.config.gicp.fine_max_correspondence_m
        cover = 2.0 * self.config.gicp.coarse_max_correspondence_m
        points = _transform(pose, frame.points[idx])
        # the nearest voxel decides a hit only within reach, and any voxel that near lies within these cells: a
        # nearest search out to `cover` cost 7 ms a frame on revisits, mostly for points with nothing near
        d, j = local.nearest(points, int(np.ceil(reach / local.voxel)), usable=subset)
        covered = (j >= 0) & (d <= min(reach, cover))
        hit = (j >= 0) & (d <= reach)
        hit[hit] = local.labels[j[hit]] == frame.labels[idx][hit]
        covered[~covered] = kernels.near_any(points[~covered], local.pos[subset], cover)
        return float(hit.mean()), float(covered.mean())

    def _commit(self, frame: _Prepared, pose: np.ndarray, moved_rows: np.ndarray, local=None,
                correction: np.ndarray | None = None, searched: bool = False, on_old_map: bool = False,
                entered: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """The only place state changes: drop moved objects from the map, record the registration window, spread a
        closed loop's correction over the map made since the anchor, merge the frame (as loop closure's old map
        allows: see VoxelPFilterMap.merge), append the pose."""
        t = len(self._poses)
        lc = self.config.loop_closure
        self._version += 1
        self._on_old_map = on_old_map
        if len(moved_rows):
            self.map.remove(moved_rows)
        if entered is not None:
            self.map.entered(*entered, t)
        if searched:
            self._last_loop_search = t
        self._drop_followed_voxels(t)
        if correction is not None:
            self._correct_map(np.linalg.inv(correction) @ pose, correction, t)
            self._loops.append((t, correction))
            local = None  # its rows and grid are stale now
        rot = pose[:3, :3]
        covs_world = kernels.rotate_covariances(frame.covs, np.ascontiguousarray(rot))
        old = t - lc.min_gap_frames if lc.enabled and t > lc.min_gap_frames else None
        self.map.merge(_transform(pose, frame.points), frame.labels, covs_world, t, local, old, on_old_map)
        self.map.compact()
        if on_old_map:
            self._anchor = t
        if t == len(self._followed_buf):  # doubled: appending stays O(1) per frame on long drives
            self._followed_buf = np.concatenate([self._followed_buf, np.zeros_like(self._followed_buf)])
        self._followed_buf[t] = on_old_map
        self._poses.append(pose)
        self._indices.append(frame.index)
        self._last = frame
