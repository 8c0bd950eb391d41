"""ReplayEnv: a scene's occupancy frames as a Gymnasium episode, scored on the caller's pose estimates.

Observation (gymnasium.spaces.Dict), a padded point set of fixed capacity:
    points  Box(grid bounds, (capacity, 3), float64)  occupied voxel centres in the ego frame, zeros past `count`
    labels  Box(0, 17, (capacity,), uint8)             Occ3D classes, 17 (free) past `count`
    count   Discrete(capacity + 1)                     how many rows are real
Action: Box((7,), float64; translation within +-1e5 m, quaternion within +-1): the caller's ego->world pose of the CURRENT frame as translation (x, y, z)
    and quaternion (qx, qy, qz, qw) (normalised here; a zero quaternion means identity), in the caller's own world.
Reward: minus the translation error (m) of that estimate after aligning the caller's first pose to the ground
    truth's first pose (est aligned = gt_0 @ inv(est_0) @ est); 0 when the scene has no ground truth.
Episode: reset() shows frame 0; each step() scores the estimate of the shown frame and shows the next one;
    `terminated` once the last frame has been scored (the last observation is repeated).
Render (render_mode="rgb_array"): a bird's-eye image of the frames so far placed by the caller's estimates (the map)
    and the estimated path, with the ground truth's path where known (occvo_core.envs.birds_eye).
Episode length: len(scene) steps; gym.make gives the environments max_episode_steps = the scene's length.
Info: frame_index, stamp (s, the data's clock), gt_pose (of the shown frame, None when unknown), and after a step:
    scored_index, translation_error, gt_pose_scored, dropped_points (points outside the grid or beyond capacity).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import FREE, OCC3D_GRID

DEFAULT_CAPACITY = 65536
MAX_TRANSLATION_M = 1e5  # action bound: any map frame on Earth's roads fits


def open_source(spec, scene: str | None = None) -> Any:
    """A SceneSource from a source, a folder (OCC-VO release or Occ3D; an Occ3D-nuScenes root with `scene`), or
    "synthetic:<seed>"."""
    if hasattr(spec, "__getitem__") and hasattr(spec, "__len__") and not isinstance(spec, (str, Path)):
        return spec
    if isinstance(spec, str) and spec.startswith("synthetic"):
        from occvo_core.sim import SyntheticScene

        _, _, seed = spec.partition(":")
        return SyntheticScene(seed=int(seed or 0))
    from occvo_core.datasets import open_scene
    from occvo_core.datasets.nuscenes_tables import is_nuscenes_root

    drive = is_nuscenes_root(Path(spec))  # a drive's occupancy here is its LiDAR's: the env runs no camera model
    return open_scene(spec, scene=scene, occupancy="lidar" if drive else None)


def _copy(obs: dict) -> dict:
    return {k: np.copy(v) if isinstance(v, np.ndarray) else v for k, v in obs.items()}


def pose_from_action(action: np.ndarray) -> np.ndarray:
    a = np.asarray(action, dtype=np.float64).reshape(7)
    pose = np.eye(4)
    q = a[3:]
    n = np.linalg.norm(q)
    if np.isfinite(n) and n > 1e-12:
        pose[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    pose[:3, 3] = a[:3]
    return pose


def action_from_pose(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    return np.concatenate([pose[:3, 3], Rotation.from_matrix(pose[:3, :3]).as_quat()])


class ReplayEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        source=None,
        capacity: int = DEFAULT_CAPACITY,
        scene_for_seed: Callable[[int], Any] | None = None,
        scene: str | None = None,
        render_mode: str | None = None,
    ):
        """source: a SceneSource, a scene folder (with `scene`: an Occ3D-nuScenes root), or "synthetic:<seed>".
        scene_for_seed: when given, reset(seed=s) replays scene_for_seed(s) instead (the synthetic environment uses it
        to draw a new town per seed)."""
        if source is None and scene_for_seed is None:
            raise ValueError("ReplayEnv needs a source or scene_for_seed")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode {render_mode!r}: this environment renders {self.metadata['render_modes']}")
        self.render_mode = render_mode
        self._birds_eye = None
        self.capacity = int(capacity)
        self.scene_for_seed = scene_for_seed
        self.source = open_source(source, scene) if source is not None else scene_for_seed(0)
        lo, hi = np.array(OCC3D_GRID.lower), np.array(OCC3D_GRID.upper)
        self.observation_space = spaces.Dict(
            {
                "points": spaces.Box(
                    np.tile(lo, (self.capacity, 1)), np.tile(hi, (self.capacity, 1)), dtype=np.float64
                ),
                "labels": spaces.Box(0, FREE, (self.capacity,), dtype=np.uint8),
                "count": spaces.Discrete(self.capacity + 1),
            }
        )
        bound = np.array([MAX_TRANSLATION_M] * 3 + [1.0] * 4)
        self.action_space = spaces.Box(-bound, bound, dtype=np.float64)
        self._index = 0
        self._first_est: np.ndarray | None = None
        self._done = False

    # -- helpers ----------------------------------------------------------------------------------
    def _gt(self, index: int) -> np.ndarray | None:
        gt = self.source.gt_poses
        return None if gt is None else np.array(gt[index])

    def _observe(self, index: int) -> tuple[dict, int]:
        frame: OccupancyFrame = self.source[index]
        self._stamp = float(frame.stamp)
        pts, labels = np.asarray(frame.points, np.float64), np.asarray(frame.labels, np.uint8)
        lo, hi = np.array(OCC3D_GRID.lower), np.array(OCC3D_GRID.upper)
        keep = np.all((pts >= lo) & (pts <= hi), axis=1)
        pts, labels = pts[keep], labels[keep]
        dropped = int((~keep).sum())
        if len(pts) > self.capacity:  # even thinning, deterministic
            sel = np.linspace(0, len(pts) - 1, self.capacity).astype(np.int64)
            dropped += len(pts) - self.capacity
            pts, labels = pts[sel], labels[sel]
        obs = {
            "points": np.zeros((self.capacity, 3)),
            "labels": np.full(self.capacity, FREE, np.uint8),
            "count": len(pts),
        }
        obs["points"][: len(pts)] = pts
        obs["labels"][: len(pts)] = labels
        return obs, dropped

    def _info(self, index: int, dropped: int) -> dict:
        return {
            "frame_index": index,
            "stamp": self._stamp,
            "gt_pose": self._gt(index),
            "dropped_points": dropped,
            "scene": self.source.name,
        }

    # -- Gymnasium API ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        scene_seed = options.get("scene_seed", seed)
        if self.scene_for_seed is not None and scene_seed is not None:
            self.source = self.scene_for_seed(int(scene_seed))
        elif "source" in options:
            self.source = open_source(options["source"])
        self._index, self._first_est, self._done = 0, None, False
        obs, dropped = self._observe(0)
        self._last_obs = _copy(obs)
        if self.render_mode == "rgb_array":
            from occvo_core.envs.birds_eye import BirdsEye

            self._birds_eye = self._birds_eye or BirdsEye()
            self._birds_eye.reset()
        return obs, self._info(0, dropped)

    def step(self, action):
        if self._done:
            raise RuntimeError("episode has terminated: call reset()")
        est = pose_from_action(action)
        scored = self._index
        if self._first_est is None:
            self._first_est = est
        gt = self._gt(scored)
        error, aligned = float("nan"), est
        if gt is not None:
            aligned = self._gt(0) @ np.linalg.inv(self._first_est) @ est
            error = float(np.linalg.norm(aligned[:3, 3] - gt[:3, 3]))
        if self._birds_eye is not None and np.all(np.isfinite(aligned)):  # the frame just scored, where it was put
            n = int(self._last_obs["count"])
            self._birds_eye.add(self._last_obs["points"][:n], self._last_obs["labels"][:n], aligned, gt)
        reward = -error if np.isfinite(error) else 0.0
        if not np.isfinite(reward):
            reward = -1e6
        terminated = scored >= len(self.source) - 1
        if terminated:
            self._done = True
            obs, dropped = _copy(self._last_obs), 0  # fresh arrays: callers keep theirs
        else:
            self._index = scored + 1
            obs, dropped = self._observe(self._index)
            self._last_obs = _copy(obs)
        info = self._info(self._index, dropped)
        info.update(scored_index=scored, translation_error=error, gt_pose_scored=gt)
        return obs, float(reward), bool(terminated), False, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._birds_eye is None:
            from occvo_core.envs.birds_eye import BirdsEye

            self._birds_eye = BirdsEye()
        return self._birds_eye.image()


def frame_from_observation(obs: dict, index: int = 0, stamp: float = 0.0) -> OccupancyFrame:
    n = int(obs["count"])
    return OccupancyFrame(
        np.asarray(obs["points"][:n], np.float64), np.asarray(obs["labels"][:n], np.uint8), index, stamp
    )


def run_occvo_agent(env: gym.Env, config=None, seed: int | None = None, options: dict | None = None) -> dict:
    """One episode with OccVO choosing the actions; returns poses, rewards and the mean translation error.
    A frame OccVO rejects is answered with its last pose (its state is unchanged by the rejection)."""
    from occvo_core.errors import InvalidFrameError
    from occvo_core.odometry import OccVO

    vo = OccVO(config)
    obs, info = env.reset(seed=seed, options=options)
    poses, rewards, errors, rejected = [], [], [], 0
    last = np.eye(4)
    while True:
        frame = frame_from_observation(obs, info["frame_index"], info.get("stamp", 0.0))
        try:
            last = vo.step(frame).pose
        except InvalidFrameError:
            rejected += 1
        poses.append(last)
        obs, reward, terminated, truncated, info = env.step(action_from_pose(last))
        rewards.append(reward)
        errors.append(info["translation_error"])
        if terminated or truncated:
            break
    errors = np.array(errors, float)
    return {
        "poses": np.array(poses),
        "rewards": np.array(rewards),
        "total_reward": float(np.sum(rewards)),
        "mean_translation_error": float(np.nanmean(errors)) if np.isfinite(errors).any() else float("nan"),
        "frames": len(poses),
        "rejected_frames": rejected,
    }
