"""SyntheticScene: a seeded town, an ego drive through it, and what the surround cameras' occupancy network would output."""

from __future__ import annotations

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.sim import render
from occvo_core.sim.agents import DynamicTrack, boxes_in_ego, make_traffic
from occvo_core.sim.noise import NoiseModel, occupied_indices
from occvo_core.sim.route import DS, lane_path, random_walk, speed_profile
from occvo_core.sim.town import RoadGraph, Terrain, Town, ZQ, build_town

# The six nuScenes cameras (ego frame, approximately their calibration): x, y, z, yaw, half horizontal FOV,
# lowest and highest elevation. Front cameras: f = 1266 px on 1600x900 images; the back camera: f = 809 px.
_HF, _VF = np.arctan(800 / 1266), np.arctan(450 / 1266)
_HB, _VB = np.arctan(800 / 809), np.arctan(450 / 809)
CAMERAS = np.array([
    [1.70, 0.02, 1.51, 0.0, _HF, -_VF, _VF],  # CAM_FRONT
    [1.52, 0.49, 1.51, np.radians(55), _HF, -_VF, _VF],  # CAM_FRONT_LEFT
    [1.55, -0.49, 1.50, np.radians(-55), _HF, -_VF, _VF],  # CAM_FRONT_RIGHT
    [1.04, 0.48, 1.56, np.radians(110), _HF, -_VF, _VF],  # CAM_BACK_LEFT
    [1.05, -0.48, 1.56, np.radians(-110), _HF, -_VF, _VF],  # CAM_BACK_RIGHT
    [0.03, 0.00, 1.58, np.pi, _HB, -_VB, _VB],  # CAM_BACK
])
# The roof lidar (for Occ3D's mask_lidar in exports): 360 deg, -30.67 .. +10.67 deg.
LIDAR = np.array([[0.94, 0.0, 1.84, 0.0, np.pi, np.radians(-30.67), np.radians(10.67)]])
D_AZ = 0.007  # ray fan spacing: 0.28 m apart at 40 m, 0.4 m at the grid's corners

_KEY_BITS = 21  # world voxel keys: three signed 21-bit integers packed in an int64


def _pack(k: np.ndarray) -> np.ndarray:
    off = 1 << (_KEY_BITS - 1)
    k = k.astype(np.int64) + off
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


def _unpack(key: np.ndarray) -> np.ndarray:
    off, m = 1 << (_KEY_BITS - 1), (1 << _KEY_BITS) - 1
    return np.column_stack([(key >> (2 * _KEY_BITS)) & m, (key >> _KEY_BITS) & m, key & m]) - off


class SyntheticScene:
    """A SceneSource over a procedural town (see occvo_core.sim for what it contains).

    Frames are rendered on demand and cached; each depends only on (seed, index), never on access order.
    Ground truth: `gt_poses` (ego->world), `static_map()`, `dynamic_tracks()`, `true_grid(i)`, `camera_mask(i)`.
    """

    def __init__(self, seed: int = 0, frames: int = 40, rate_hz: float = 2.0, noise: NoiseModel | str | dict | None = "default",
                 traffic: bool = True):
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
        if not isinstance(frames, (int, np.integer)) or frames < 1:
            raise ConfigError(f"frames must be a positive integer, got {frames!r}")
        if not rate_hz > 0:
            raise ConfigError(f"rate_hz must be positive, got {rate_hz!r}")
        try:
            self.noise = NoiseModel.coerce(noise)
        except ValueError as exc:
            raise ConfigError(f"noise: {exc}") from None
        self.seed, self.frames, self.rate_hz, self.traffic = int(seed), int(frames), float(rate_hz), bool(traffic)
        self.name = f"synthetic-{self.seed:04d}"
        self.times = np.arange(self.frames) / self.rate_hz
        duration = float(self.times[-1])
        ss = np.random.SeedSequence(self.seed)
        r_terrain, r_graph, r_route, r_traffic = (np.random.default_rng(s) for s in ss.spawn(4))
        self.terrain = Terrain.random(r_terrain)
        self.graph = RoadGraph.random(r_graph, extent=15.0 * duration + 150.0)
        self.motion = self._plan_ego(r_route, duration)
        xy, heading = self.motion.xy_heading(self.times)
        self.speeds = self.motion.speed_at(self.times)
        lower, upper = xy.min(axis=0) - 62.0, xy.max(axis=0) + 62.0
        self.town: Town = build_town(self.seed, self.graph, self.terrain, lower, upper)
        self._poses = self._ego_poses(xy, heading)
        scale = min(max(1.0, duration / 20.0), 4.0)  # longer drives see more of the town, up to a point
        n_veh = int(r_traffic.integers(6, 11) * scale) if traffic else 0
        n_ped = int(r_traffic.integers(8, 16) * scale) if traffic else 0
        self.tracks: list[DynamicTrack] = make_traffic(self.town, r_traffic, self.times, xy, lower, upper, n_veh, n_ped)
        self._frames: dict[int, OccupancyFrame] = {}
        self._static: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (world voxel keys, labels) seen

    # -- the ego drive -------------------------------------------------------------------------------
    def _plan_ego(self, rng: np.random.Generator, duration: float):
        g = self.graph
        degree = np.array([len(n) for n in g.neighbours])
        d = np.linalg.norm(g.nodes, axis=1) + np.where(degree >= 3, 0.0, 1e6)
        first = int(np.argmin(d))  # an intersection near the origin: the first stop and turn
        options = [n for n in g.neighbours[first] if np.linalg.norm(g.nodes[n] - g.nodes[first]) > 45.0] or g.neighbours[first]
        prev = options[rng.integers(len(options))]
        nodes = random_walk(g, rng, first, prev, 15.0 * duration + 120.0, force_turn_first=True)
        path = lane_path(g, nodes)
        start = max(path.node_s[0] - rng.uniform(30.0, 42.0), 0.0)
        k0 = int(start / DS)
        path.xy, path.heading, path.curvature = path.xy[k0:], path.heading[k0:], path.curvature[k0:]
        path.node_s = path.node_s - k0 * DS
        v_cruise = np.empty(len(path.xy))
        bounds = np.concatenate([[0.0], path.node_s, [np.inf]])
        s = np.arange(len(path.xy)) * DS
        for a, b in zip(bounds[:-1], bounds[1:]):
            v_cruise[(s >= a) & (s < b)] = rng.uniform(8.0, 13.5)
        stops = []
        for i, (node, ns) in enumerate(zip(nodes[1:-1], path.node_s)):
            stop_line = ns - 13.0  # just before the turn curve, which starts 12 m before the node
            if stop_line > 0 and (i == 0 or rng.random() < 0.25):
                stops.append((stop_line, rng.uniform(2.0, 4.0) if i == 0 else rng.uniform(1.5, 3.0)))
        self.stops = stops
        return speed_profile(path, v_cruise, v0=rng.uniform(4.0, 9.0), stops=stops)

    def _ego_poses(self, xy: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Ego frame on the ground under the rear axle, x forward, z along the ground normal."""
        gx, gy = self.terrain.gradient(xy[:, 0], xy[:, 1])
        n = np.column_stack([-gx, -gy, np.ones(len(xy))])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        f = np.column_stack([np.cos(heading), np.sin(heading), np.zeros(len(xy))])
        f -= np.sum(f * n, axis=1, keepdims=True) * n
        f /= np.linalg.norm(f, axis=1, keepdims=True)
        poses = np.tile(np.eye(4), (len(xy), 1, 1))
        poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2] = f, np.cross(n, f), n
        poses[:, :2, 3] = xy
        poses[:, 2, 3] = self.terrain.height(xy[:, 0], xy[:, 1])
        return poses

    # -- SceneSource ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.frames

    @property
    def gt_poses(self) -> np.ndarray:
        return self._poses.copy()

    def __getitem__(self, index: int) -> OccupancyFrame:
        index = self._check(index)
        if index not in self._frames:
            static, full = self._render(index)
            mask = self._visible(full, CAMERAS)
            self._remember_static(index, static, full, mask)
            noisy = self.noise.apply(full, mask, np.random.default_rng([self.seed, index, 0x0CC]), self._poses[index], self.seed)
            idx = occupied_indices(noisy)
            frame = OccupancyFrame(OCC3D_GRID.centres_of(idx), noisy[idx[:, 0], idx[:, 1], idx[:, 2]], index,
                                   float(self.times[index]), {"scene": self.name, "source": "synthetic"})
            self._frames[index] = frame
        f = self._frames[index]
        return OccupancyFrame(f.points.copy(), f.labels.copy(), f.index, f.stamp, dict(f.meta))

    def _check(self, index: int) -> int:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(index).__name__}")
        if index < 0:
            index += self.frames
        if not 0 <= index < self.frames:
            raise IndexError(index)
        return int(index)

    # -- ground truth --------------------------------------------------------------------------------
    def true_grid(self, index: int) -> np.ndarray:
        """Noise-free occupancy (200,200,16) uint8 in the ego frame, before the visibility pass (17 = free)."""
        return self._render(self._check(index))[1]

    def camera_mask(self, index: int) -> np.ndarray:
        """(200,200,16) bool: voxels some camera ray reaches (free ones included), the surface hit included."""
        return self._visible(self.true_grid(index), CAMERAS)

    def lidar_mask(self, index: int) -> np.ndarray:
        """As camera_mask for the roof lidar, for exports in the Occ3D layout."""
        return self._visible(self.true_grid(index), LIDAR)

    def static_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The true static world map: world-frame 0.4 m voxel centres and classes of everything that never moves
        (STATIC_CLASSES and parked vehicles, which carry their movable class) and that some camera saw in some
        frame, noise-free. Map metrics keep STATIC_CLASSES only, so parked vehicles drop out there.
        Each world voxel takes its class from the earliest frame that saw it."""
        for i in range(self.frames):
            if i not in self._static:
                static, full = self._render(i)
                self._remember_static(i, static, full, self._visible(full, CAMERAS))
        keys = np.concatenate([self._static[i][0] for i in range(self.frames)])
        labels = np.concatenate([self._static[i][1] for i in range(self.frames)])
        keys, first = np.unique(keys, return_index=True)  # stable: earliest frame first
        return (_unpack(keys) + 0.5) * OCC3D_GRID.voxel_size, labels[first]

    def dynamic_tracks(self) -> list[DynamicTrack]:
        """Moving vehicles and pedestrians with their world poses at every frame (parked vehicles are in static_map)."""
        return list(self.tracks)

    # -- rendering -----------------------------------------------------------------------------------
    def _render(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(static-only grid, full grid with moving agents), both noise-free and before visibility."""
        pose = self._poses[index]
        t = self.town
        static = render.empty_grid()
        render.render_static(pose[:3, :3].copy(), pose[:3, 3].copy(), t.h_base, t.raise_cm, t.ground, t.layers,
                             float(t.origin[0]), float(t.origin[1]), 0.2, ZQ, render.LOWER, render.VOXEL, static)
        full = static.copy()
        if self.tracks:
            render.render_boxes(boxes_in_ego(self.tracks, index, pose), render.LOWER, render.VOXEL, full)
        return static, full

    @staticmethod
    def _visible(grid: np.ndarray, sensors: np.ndarray) -> np.ndarray:
        mask = np.zeros(grid.shape, np.bool_)
        render.visibility(grid != FREE, sensors, render.LOWER, render.VOXEL, D_AZ, mask)
        return mask

    def _remember_static(self, index: int, static: np.ndarray, full: np.ndarray, mask: np.ndarray) -> None:
        seen = (static != FREE) & (full == static) & mask
        idx = render.nonzero3(seen, True, True)
        world = OCC3D_GRID.centres_of(idx) @ self._poses[index][:3, :3].T + self._poses[index][:3, 3]
        keys = _pack(np.floor(world / OCC3D_GRID.voxel_size).astype(np.int64))
        self._static[index] = (keys, static[seen])


__all__ = ["SyntheticScene", "CAMERAS", "LIDAR"]
