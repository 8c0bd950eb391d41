"""SyntheticScene: a seeded town, an ego drive through it, and what the surround cameras' occupancy network would output."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.sim import render
from occvo_core.sim.agents import DynamicTrack, boxes_in_ego, loop_traffic, make_traffic
from occvo_core.sim.noise import NoiseModel, occupied_indices
from occvo_core.sim.raster import ZQ, Town
from occvo_core.sim.roads import RoadGraph, Terrain
from occvo_core.sim.route import DS, block_loop, lane_path, random_walk, speed_profile
from occvo_core.sim.town import build_town

# The six nuScenes cameras (ego frame, approximately their calibration): x, y, z, yaw, half horizontal FOV,
# lowest and highest elevation. Front cameras: f = 1266 px on 1600x900 images; the back camera: f = 809 px.
_HF, _VF = np.arctan(800 / 1266), np.arctan(450 / 1266)
_HB, _VB = np.arctan(800 / 809), np.arctan(450 / 809)
CAMERAS = np.array(
    [
        [1.70, 0.02, 1.51, 0.0, _HF, -_VF, _VF],  # CAM_FRONT
        [1.52, 0.49, 1.51, np.radians(55), _HF, -_VF, _VF],  # CAM_FRONT_LEFT
        [1.55, -0.49, 1.50, np.radians(-55), _HF, -_VF, _VF],  # CAM_FRONT_RIGHT
        [1.04, 0.48, 1.56, np.radians(110), _HF, -_VF, _VF],  # CAM_BACK_LEFT
        [1.05, -0.48, 1.56, np.radians(-110), _HF, -_VF, _VF],  # CAM_BACK_RIGHT
        [0.03, 0.00, 1.58, np.pi, _HB, -_VB, _VB],  # CAM_BACK
    ]
)
# The roof lidar (for Occ3D's mask_lidar in exports): 360 deg, -30.67 .. +10.67 deg.
LIDAR = np.array([[0.94, 0.0, 1.84, 0.0, np.pi, np.radians(-30.67), np.radians(10.67)]])

LONG_DRIVE = 500  # frames: longer drives keep only a few frames cached and no per-frame static bookkeeping
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

    route="walk" (default): a random drive through a town that grows with the drive.
    route="loop": lap after lap of a closed circuit around `loop_blocks` (nx, ny) city blocks (4 x 4: about
    1.1 km), the town built only over the circuit plus the sensor range; `lap_starts` are the frames at which
    each lap begins (the ego back at its start) and `lap_length_m` the circuit's length.
    cache_frames: frames kept rendered (least recently used go first); None keeps all for drives of up to
    LONG_DRIVE frames and 8 beyond. keep_static: keep per-frame static voxels for static_map() (None: only up
    to LONG_DRIVE frames; without them static_map() renders the drive again).
    """

    def __init__(
        self,
        seed: int = 0,
        frames: int = 40,
        rate_hz: float = 2.0,
        noise: NoiseModel | str | dict | None = "default",
        traffic: bool = True,
        route: str = "walk",
        loop_blocks: tuple[int, int] = (4, 4),
        cache_frames: int | None = None,
        keep_static: bool | None = None,
    ):
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
        if not isinstance(frames, (int, np.integer)) or frames < 1:
            raise ConfigError(f"frames must be a positive integer, got {frames!r}")
        if not rate_hz > 0:
            raise ConfigError(f"rate_hz must be positive, got {rate_hz!r}")
        if route not in ("walk", "loop"):
            raise ConfigError(f"route must be 'walk' or 'loop', got {route!r}")
        if cache_frames is not None and (not isinstance(cache_frames, (int, np.integer)) or cache_frames < 0):
            raise ConfigError(f"cache_frames must be a non-negative integer or None, got {cache_frames!r}")
        try:
            self.noise = NoiseModel.coerce(noise)
        except ValueError as exc:
            raise ConfigError(f"noise: {exc}") from None
        self.seed, self.frames, self.rate_hz, self.traffic = int(seed), int(frames), float(rate_hz), bool(traffic)
        self.route = route
        self.name = f"synthetic-{self.seed:04d}" if route == "walk" else f"synthetic-loop-{self.seed:04d}"
        long = self.frames > LONG_DRIVE
        self.cache_frames = (8 if long else None) if cache_frames is None else int(cache_frames)  # None: all
        self.keep_static = (not long) if keep_static is None else bool(keep_static)
        self.times = np.arange(self.frames) / self.rate_hz
        duration = float(self.times[-1])
        ss = np.random.SeedSequence(self.seed)
        r_terrain, r_graph, r_route, r_traffic = (np.random.default_rng(s) for s in ss.spawn(4))
        self.terrain = Terrain.random(r_terrain)
        if route == "loop":
            try:
                self.loop_blocks = (int(loop_blocks[0]), int(loop_blocks[1]))
            except (TypeError, ValueError, IndexError):
                raise ConfigError(f"loop_blocks must be two block counts (nx, ny), got {loop_blocks!r}") from None
            if min(self.loop_blocks) < 1 or max(self.loop_blocks) > 12:
                raise ConfigError(f"loop_blocks must be 1..12 blocks a side, got {loop_blocks!r}")
            self.graph = RoadGraph.random(r_graph, extent=42.5 * max(self.loop_blocks) + 200.0)
            self.motion = self._plan_loop(r_route, duration)
        else:
            self.graph = RoadGraph.random(r_graph, extent=15.0 * duration + 150.0)
            self.motion = self._plan_ego(r_route, duration)
        xy, heading = self.motion.xy_heading(self.times)
        self.speeds = self.motion.speed_at(self.times)
        lower, upper = xy.min(axis=0) - 62.0, xy.max(axis=0) + 62.0
        self.town: Town = build_town(self.seed, self.graph, self.terrain, lower, upper)
        self._poses = self._ego_poses(xy, heading)
        scale = min(max(1.0, duration / 20.0), 4.0)  # longer drives see more of the town, up to a point
        if route == "loop":
            self.tracks = self._loop_traffic(r_traffic, xy, lower, upper, scale) if traffic else []
        else:
            n_veh = int(r_traffic.integers(6, 11) * scale) if traffic else 0
            n_ped = int(r_traffic.integers(8, 16) * scale) if traffic else 0
            self.tracks: list[DynamicTrack] = make_traffic(
                self.town, r_traffic, self.times, xy, lower, upper, n_veh, n_ped
            )
        self._frames: OrderedDict[int, OccupancyFrame] = OrderedDict()
        self._static: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (world voxel keys, labels) seen

    # -- the ego drive -------------------------------------------------------------------------------
    def _plan_ego(self, rng: np.random.Generator, duration: float):
        g = self.graph
        degree = np.array([len(n) for n in g.neighbours])
        d = np.linalg.norm(g.nodes, axis=1) + np.where(degree >= 3, 0.0, 1e6)
        first = int(np.argmin(d))  # an intersection near the origin: the first stop and turn
        options = [
            n for n in g.neighbours[first] if np.linalg.norm(g.nodes[n] - g.nodes[first]) > 45.0
        ] or g.neighbours[first]
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
        for i, (_node, ns) in enumerate(zip(nodes[1:-1], path.node_s)):
            stop_line = ns - 13.0  # just before the turn curve, which starts 12 m before the node
            if stop_line > 0 and (i == 0 or rng.random() < 0.25):
                stops.append((stop_line, rng.uniform(2.0, 4.0) if i == 0 else rng.uniform(1.5, 3.0)))
        self.stops = stops
        return speed_profile(path, v_cruise, v0=rng.uniform(4.0, 9.0), stops=stops)

    def _plan_loop(self, rng: np.random.Generator, duration: float):
        """Laps of a block circuit; cruise speeds per road and stops per intersection repeat every lap."""
        g = self.graph
        try:
            cycle = block_loop(g, rng, self.loop_blocks)
        except ValueError as exc:
            raise ConfigError(f"loop_blocks {self.loop_blocks}: {exc}") from None
        m = len(cycle)
        one_lap = sum(
            float(np.sum(np.linalg.norm(np.diff(g.path(a, b), axis=0), axis=1)))
            for a, b in zip(cycle, cycle[1:] + cycle[:1])
        )
        # room for the drive plus two laps, so that traffic driving the ego's profile ahead of it has road
        laps = int(np.ceil((15.0 * duration + 220.0) / one_lap)) + 2
        nodes = cycle * laps + cycle[:2]
        path = lane_path(g, nodes)
        v_road = rng.uniform(8.0, 13.5, m)  # per road of the circuit: road j goes from cycle[j] to cycle[j+1]
        stop_at = rng.random(m) < 0.25
        stop_at[1 % m] = True  # the first intersection, as in a random drive
        dwell = rng.uniform(1.5, 3.0, m)
        start = max(path.node_s[0] - rng.uniform(30.0, 42.0), 0.0)
        k0 = int(start / DS)
        path.xy, path.heading, path.curvature = path.xy[k0:], path.heading[k0:], path.curvature[k0:]
        path.node_s = path.node_s - k0 * DS
        s = np.arange(len(path.xy)) * DS
        v_cruise = np.empty(len(path.xy))
        bounds = np.concatenate([[-np.inf], path.node_s, [np.inf]])
        for j, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
            v_cruise[(s >= a) & (s < b)] = v_road[j % m]
        stops = [
            (ns - 13.0, float(dwell[(i + 1) % m]))
            for i, ns in enumerate(path.node_s)
            if stop_at[(i + 1) % m] and ns - 13.0 > 0
        ]
        self.stops = stops
        self.cycle = cycle
        self.lap_length_m = float(path.node_s[m] - path.node_s[0])
        motion = speed_profile(path, v_cruise, v0=rng.uniform(4.0, 9.0), stops=stops)
        s_frames = motion.s_at(self.times)
        n_laps = int(s_frames[-1] // self.lap_length_m)
        self.lap_starts = np.array(
            [0] + [int(np.searchsorted(s_frames, k * self.lap_length_m)) for k in range(1, n_laps + 1)]
        )
        return motion

    def _loop_traffic(
        self, rng: np.random.Generator, xy: np.ndarray, lower: np.ndarray, upper: np.ndarray, scale: float
    ) -> list[DynamicTrack]:
        """Vehicles on the circuit (ahead in the ego's lane, oncoming in the other), pedestrians as usual."""
        n_ahead, n_oncoming = int(rng.integers(2, 5)), int(rng.integers(3, 7))
        n_ped = int(rng.integers(8, 16) * scale)
        cars, placed = loop_traffic(
            self.town, rng, self.times, self.motion, self.cycle, self.lap_length_m, n_ahead, n_oncoming
        )
        return cars + make_traffic(
            self.town, rng, self.times, xy, lower, upper, 0, n_ped, avoid=placed, first_id=len(cars)
        )

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
            if self.keep_static:
                self._remember_static(index, static, full, mask)
            noisy = self.noise.apply(
                full, mask, np.random.default_rng([self.seed, index, 0x0CC]), self._poses[index], self.seed
            )
            idx = occupied_indices(noisy)
            frame = OccupancyFrame(
                OCC3D_GRID.centres_of(idx),
                noisy[idx[:, 0], idx[:, 1], idx[:, 2]],
                index,
                float(self.times[index]),
                {"scene": self.name, "source": "synthetic"},
            )
            if self.cache_frames != 0:
                self._frames[index] = frame
                if self.cache_frames is not None and len(self._frames) > self.cache_frames:
                    self._frames.popitem(last=False)
        else:
            frame = self._frames[index]
            if self.cache_frames is not None:
                self._frames.move_to_end(index)
        f = frame
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

    def static_map(self, frames=None) -> tuple[np.ndarray, np.ndarray]:
        """The true static world map: world-frame 0.4 m voxel centres and classes of everything that never moves
        (STATIC_CLASSES and parked vehicles, which carry their movable class) and that some camera saw in some
        frame, noise-free. Map metrics keep STATIC_CLASSES only, so parked vehicles drop out there.
        Each world voxel takes its class from the earliest frame that saw it. `frames`: only what those saw."""
        if frames is not None:
            return self._static_map_streamed(sorted({self._check(int(i)) for i in frames}))
        if not self.keep_static:
            return self._static_map_streamed(range(self.frames))
        for i in range(self.frames):
            if i not in self._static:
                static, full = self._render(i)
                self._remember_static(i, static, full, self._visible(full, CAMERAS))
        keys = np.concatenate([self._static[i][0] for i in range(self.frames)])
        labels = np.concatenate([self._static[i][1] for i in range(self.frames)])
        keys, first = np.unique(keys, return_index=True)  # stable: earliest frame first
        return (_unpack(keys) + 0.5) * OCC3D_GRID.voxel_size, labels[first]

    def _static_map_streamed(self, frames) -> tuple[np.ndarray, np.ndarray]:
        """static_map() without per-frame bookkeeping: frames rendered again in order, the map merged as it
        grows (memory bounded by the map, not the drive). Same result as static_map() with keep_static."""
        keys, labels = np.zeros(0, np.int64), np.zeros(0, np.uint8)
        for i in frames:
            static, full = self._render(i)
            k, lab = self._static_of(i, static, full, self._visible(full, CAMERAS))
            keys, first = np.unique(np.concatenate([keys, k]), return_index=True)  # earlier entries win
            labels = np.concatenate([labels, lab])[first]
        return (_unpack(keys) + 0.5) * OCC3D_GRID.voxel_size, labels

    def dynamic_tracks(self) -> list[DynamicTrack]:
        """Moving vehicles and pedestrians with their world poses at every frame (parked vehicles are in static_map)."""
        return list(self.tracks)

    # -- rendering -----------------------------------------------------------------------------------
    def _render(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(static-only grid, full grid with moving agents), both noise-free and before visibility."""
        pose = self._poses[index]
        t = self.town
        static = render.empty_grid()
        render.render_static(
            pose[:3, :3].copy(),
            pose[:3, 3].copy(),
            t.h_base,
            t.raise_cm,
            t.ground,
            t.layers,
            float(t.origin[0]),
            float(t.origin[1]),
            0.2,
            ZQ,
            render.LOWER,
            render.VOXEL,
            static,
        )
        full = static.copy()
        if self.tracks:
            render.render_boxes(boxes_in_ego(self.tracks, index, pose), render.LOWER, render.VOXEL, full)
        return static, full

    @staticmethod
    def _visible(grid: np.ndarray, sensors: np.ndarray) -> np.ndarray:
        return render.visible(grid, sensors)

    def _remember_static(self, index: int, static: np.ndarray, full: np.ndarray, mask: np.ndarray) -> None:
        self._static[index] = self._static_of(index, static, full, mask)

    def _static_of(
        self, index: int, static: np.ndarray, full: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        seen = (static != FREE) & (full == static) & mask
        idx = render.nonzero3(seen, True, True)
        world = OCC3D_GRID.centres_of(idx) @ self._poses[index][:3, :3].T + self._poses[index][:3, 3]
        keys = _pack(np.floor(world / OCC3D_GRID.voxel_size).astype(np.int64))
        return keys, static[seen]


__all__ = ["SyntheticScene", "CAMERAS", "LIDAR"]
