"""Loop closure (beyond the paper: its scenes are 20 s long): back at a place mapped long ago with drift beyond
GICP's reach, find the frame on that old map, relocalise it, and spread the correction over the map made since.

LoopClosure keeps what closing loops needs between frames: the closures made, where the last one was searched,
whether the last frame lay on the old map (and the last frame that did: the anchor), which frames followed the old
map, and per closure the correction of the map made at each frame (so a tile paged out before it comes back moved)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.config import OccVOConfig
from occvo_core.grid import GROUND_CLASSES, MOVABLE_CLASSES
from occvo_core.registration.gicp import coarse_gicp, fine_gicp
from occvo_core.registration.initialisation import bev_first_motion, ground_height_correction
from occvo_core.registration.kernels.nearest import near_any
from occvo_core.registration.local_map import EgoMap, LocalMap, frame_window, moved, transform, window_margin
from occvo_core.registration.preprocess import Prepared
from occvo_core.registration.voxel_map import VoxelPFilterMap
from occvo_core.registration.voxel_rows import _field


class LoopClosure:
    def __init__(self, config: OccVOConfig, voxel_map: VoxelPFilterMap):
        self.config = config
        self.map = voxel_map
        self.margin = window_margin(config.voxel_pfilter.window_margin_m)
        self.loops: list[tuple[int, np.ndarray]] = []  # (frame, correction) of every loop closed
        self.last_search = -(1 << 30)  # frame of the last loop search
        self.on_old_map = False  # the last frame lay on the old map (lock_share)
        self.anchor = 0  # the last frame on the old map (or the first): the map since then drifted with the poses
        self._followed_buf = np.zeros(256, bool)  # per frame: it followed the old map (its new voxels are recent map)
        self.frames = 0  # frames committed
        # per loop closed: the frames (anchor, t] and the world -> world correction of the map made at each
        self.map_corrections: list[tuple[int, np.ndarray, np.ndarray]] = []

    @property
    def followed(self) -> np.ndarray:
        """Per committed frame: it followed the old map."""
        return self._followed_buf[: self.frames]

    def correction_at(self, t: int) -> np.ndarray | None:
        """The correction of the loop closed at frame t, if one was."""
        return self.loops[-1][1] if self.loops and self.loops[-1][0] == t else None

    # -- registration ----------------------------------------------------------------------------------------
    def old_map(self, local: LocalMap, t: int) -> np.ndarray | None:
        """Mask of the window's voxels that are the old map: made at least min_gap_frames ago, and reliable while
        they were in view (their p-index now also counts the frames since). None when off or too early."""
        lc = self.config.loop_closure
        if not lc.enabled or t <= lc.min_gap_frames:
            return None
        return self.map.persistent_rows(local.rows, born_before=t - lc.min_gap_frames)

    def follow(self, local: LocalMap, old: np.ndarray | None) -> None:
        """Following a place mapped long ago, its map constrains registration whatever its p-index."""
        if self.on_old_map:
            local.usable |= old

    def old_born_before(self, t: int) -> int | None:
        """Frame t's merge leaves the voxels made before this frame as the old map (VoxelPFilterMap.merge)."""
        lc = self.config.loop_closure
        return t - lc.min_gap_frames if lc.enabled and t > lc.min_gap_frames else None

    def search(
        self, frame: Prepared, pose: np.ndarray, t: int, local: LocalMap, old: np.ndarray | None
    ) -> tuple[np.ndarray | None, dict[str, int]]:
        """Find the frame on the old map (a BEV correlation over metres, then coarse and fine GICP against the old
        voxels alone) and return the correction (world -> world) when it puts far more of the frame on the old map
        than the registered pose does. info["loop_on_old"]: the frame (relocalised or not) lies on the old map."""
        lc = self.config.loop_closure
        if old is None:
            return None, {}
        info = {"loop_old_voxels": int(old.sum())}
        if info["loop_old_voxels"] < lc.min_old_voxels:
            return None, info
        # the share is judged on static structure: ground lies on old ground at any offset along a road
        src = frame.fine[~np.isin(frame.labels[frame.fine], GROUND_CLASSES + MOVABLE_CLASSES)]
        share, covered = self.share_on(frame, src, pose, local, old)
        info["loop_share_pct"] = int(round(100 * share))
        info["loop_on_old"] = int(covered >= lc.min_overlap and share >= lc.lock_share)
        if share >= lc.lock_share or len(src) == 0 or t - self.last_search < lc.search_every_frames:
            return None, info
        info["loop_searched"] = 1
        unexplained = self._unexplained(frame, pose, local, old)
        local = self._search_window(pose, t)
        old = self.old_map(local, t)
        relocalised = self._relocalise(frame, pose, unexplained, local, old)
        found, covered = self.share_on(frame, src, relocalised, local, old)
        jump = float(np.linalg.norm(relocalised[:3, 3] - pose[:3, 3]))
        on_covered = found / max(covered, 1e-9)
        info.update(
            loop_found_pct=int(round(100 * found)),
            loop_covered_pct=int(round(100 * covered)),
            loop_jump_mm=int(round(1000 * jump)),
        )
        # judged where the old map is: coming back, a frame still sees the road it came by, which the old map lacks
        if on_covered < lc.accept_share or covered < lc.min_overlap or found < 2 * share or jump < lc.min_correction_m:
            return None, info
        info["loop_closed"] = info["loop_on_old"] = 1
        return relocalised @ np.linalg.inv(pose), info

    def _unexplained(self, frame: Prepared, pose: np.ndarray, local: LocalMap, old: np.ndarray) -> np.ndarray:
        """Mask of the frame's points the recent map does not explain at pose. What it explains is the road just
        driven: the rest is what must be found on the old map (the trail's trees and houses would alias the search)."""
        reach = self.config.gicp.fine_max_correspondence_m
        d, _ = local.nearest(
            transform(pose, frame.points), int(np.ceil(reach / local.voxel)), usable=local.alive() & ~old
        )
        return d > reach

    def _search_window(self, pose: np.ndarray, t: int) -> LocalMap:
        """The old map as far around the frame as the search reaches, not just its registration window."""
        lc = self.config.loop_closure
        return frame_window(
            self.map, pose, t, self.margin + [lc.search_radius_m, lc.search_radius_m, lc.search_height_m], tight=True
        )

    def _relocalise(
        self, frame: Prepared, pose: np.ndarray, unexplained: np.ndarray, local: LocalMap, old: np.ndarray
    ) -> np.ndarray:
        """The frame's pose on the old map: its unexplained points correlated with the old map in BEV, levelled on
        its ground, then coarse and fine GICP against it."""
        lc = self.config.loop_closure
        motion, _ = bev_first_motion(
            transform(np.linalg.inv(pose), local.pos[old]),
            local.labels[old],
            frame.points[unexplained],
            frame.labels[unexplained],
            search_radius_m=lc.search_radius_m,
            yaw_steps_deg=lc.yaw_steps_deg,
        )
        candidate = pose @ motion
        # height, roll and pitch drift too on a long drive: level the frame's ground on the old map's
        level = ground_height_correction(
            local.pos[old & np.isin(local.labels, GROUND_CLASSES)],
            transform(candidate, frame.points[np.isin(frame.labels, GROUND_CLASSES)]),
            candidate[:3, 3],
        )
        if level is not None:
            candidate = level @ candidate
        ego = EgoMap.around(local, candidate, self.margin, subset=old)
        coarse = coarse_gicp(frame, ego, self.config)  # with its wide pass: the BEV peak can be metres off
        return candidate @ fine_gicp(frame, frame.fine, ego, coarse.pose, self.config).pose

    def share_on(
        self, frame: Prepared, idx: np.ndarray, pose: np.ndarray, local: LocalMap, subset: np.ndarray
    ) -> tuple[float, float]:
        """Shares of frame points idx that, at pose, have a voxel of subset with their label within the fine GICP
        correspondence distance, and that have one of any label within twice the coarse correspondence distance
        (the part of the frame the subset covers)."""
        if len(idx) == 0:
            return 0.0, 0.0
        reach = self.config.gicp.fine_max_correspondence_m
        cover = 2.0 * self.config.gicp.coarse_max_correspondence_m
        points = transform(pose, frame.points[idx])
        # the nearest voxel decides a hit only within reach, and any voxel that near lies within these cells; the
        # rest only needs to know whether anything lies within `cover`
        d, j = local.nearest(points, int(np.ceil(reach / local.voxel)), usable=subset)
        covered = (j >= 0) & (d <= min(reach, cover))
        hit = (j >= 0) & (d <= reach)
        hit[hit] = local.labels[j[hit]] == frame.labels[idx][hit]
        covered[~covered] = near_any(points[~covered], local.pos[subset], cover)
        return float(hit.mean()), float(covered.mean())

    # -- the map update --------------------------------------------------------------------------------------
    def before_merge(
        self,
        poses: list[np.ndarray],
        pose: np.ndarray,
        t: int,
        correction: np.ndarray | None,
        searched: bool,
        on_old_map: bool,
    ) -> bool:
        """Frame t is committed at `pose` (after `poses`): drop the voxels of followed frames that come of age and
        spread a closed loop's correction over the map. Returns whether the map moved (windows are stale)."""
        self.on_old_map = on_old_map
        if searched:
            self.last_search = t
        self.drop_followed_voxels(t)
        if correction is None:
            return False
        self.correct_map(poses, np.linalg.inv(correction) @ pose, correction, t)
        self.loops.append((t, correction))
        return True

    def after_merge(self, t: int, on_old_map: bool) -> None:
        if on_old_map:
            self.anchor = t
        if t == len(self._followed_buf):  # doubled: appending stays O(1) per frame on long drives
            self._followed_buf = np.concatenate([self._followed_buf, np.zeros_like(self._followed_buf)])
        self._followed_buf[t] = on_old_map
        self.frames = t + 1

    def correct_map(self, poses: list[np.ndarray], pose: np.ndarray, correction: np.ndarray, t: int) -> None:
        """Spread the loop correction over the map made since the anchor (the last frame on the old map), as a pose
        graph with equal weights along the path would: each frame's heading takes the rotation in proportion to
        the distance driven since the anchor, the path is integrated again with it, and what is left of the
        translation is spread the same way. Each voxel moves with the frame that made it, so the last frame gets
        the whole correction and the anchor none. Moved voxels that land on the anchor's map are dropped as ghosts
        of it (VoxelPFilterMap.move)."""
        a = self.anchor
        frames = np.arange(a + 1, t + 1)
        ego = np.array([p[:3, 3] for p in poses[a:]] + [pose[:3, 3]])  # frames a..t, registered
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
        self.map_corrections.append((t, frames, corrections))
        rows = self.map.live_rows(born_after=a)
        self.map.move(
            rows,
            corrections[:, :3, :3],
            corrections[:, :3, 3],
            ghost_radius_m=self.config.loop_closure.ghost_radius_m,
            born_before=a + 1,
            group=self.map.born_of(rows) - a - 1,
        )

    def drop_followed_voxels(self, t: int, restored: bool = False) -> None:
        """Voxels made by frames that followed the old map are the recent map registration needs where that map is
        thin, never old map themselves: dropped before they would be (min_gap_frames old), or a lap that slipped
        along a street of repeated structure would leave its copy of the place there to pull the next laps the
        same way. Per frame only frame t - min_gap_frames comes of age (one scan, and only if it followed); tiles
        just restored may hold voxels of any earlier frame."""
        b = t - self.config.loop_closure.min_gap_frames
        if b < 0 or not (self.followed[: b + 1].any() if restored else self.followed[b]):
            return
        if restored:
            rows = self.map.live_rows(born_up_to=b)
            rows = rows[self.followed[self.map.born_of(rows)]]
        else:
            rows = self.map.live_rows(born_at=b)
        if len(rows):
            self.map.remove(rows)

    def corrected_block(self, block: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A paged-out block of voxels as the loops closed since it was taken would have moved it (correct_map)."""
        taken = int(block["taken_at"])
        later = [c for c in self.map_corrections if c[0] >= taken]
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

    # -- state -----------------------------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        rows = [[t, b, *c.ravel()] for t, frames, cs in self.map_corrections for b, c in zip(frames, cs)]
        return {
            "loops": np.array([[t, *c.ravel()] for t, c in self.loops], np.float64).reshape(-1, 17),
            "last_loop_search": np.array(self.last_search, np.int64),
            "on_old_map": np.array(self.on_old_map),
            "anchor": np.array(self.anchor, np.int64),
            "followed_frames": np.flatnonzero(self.followed).astype(np.int64),
            "map_corrections": np.array(rows, np.float64).reshape(-1, 18),
        }

    def load_state(self, state: dict[str, np.ndarray], frames: int) -> None:
        """state() of a run with `frames` frames committed; keys it lacks keep their start values."""
        loops = np.asarray(state.get("loops", np.zeros((0, 17))))
        self.loops = [(int(row[0]), row[1:].reshape(4, 4).copy()) for row in loops]
        self.last_search = int(state.get("last_loop_search", self.last_search))
        self.on_old_map = bool(state.get("on_old_map", False))
        self.anchor = int(state.get("anchor", 0))
        self.frames = frames
        self._followed_buf = np.zeros(max(256, 2 * frames), bool)
        self._followed_buf[np.asarray(state.get("followed_frames", np.zeros(0, np.int64)), np.int64)] = True
        rows = np.asarray(state.get("map_corrections", np.zeros((0, 18))))
        for t in np.unique(rows[:, 0]).astype(np.int64):
            mine = rows[rows[:, 0] == t]
            self.map_corrections.append((int(t), mine[:, 1].astype(np.int64), mine[:, 2:].reshape(-1, 4, 4).copy()))
