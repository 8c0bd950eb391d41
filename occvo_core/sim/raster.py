"""The synthetic town's world model: Occ3D classes, the 2.5-D raster it is stored on, and the painter that draws on it.

The world is stored 2.5-D on a 0.2 m raster (small and fast to sample): per cell a ground class and kerb
raise, and two object layers (label, bottom, top) so a tree crown can hang over its trunk or a parked car.
Heights are relative to a gently rolling terrain h(x, y), which gives the ego real pitch, roll and z motion.
Thin things (poles, cones, sign plates, trunks) are drawn at least 0.5 m wide so that the 0.4 m
occupancy voxels they cross are occupied, as a lidar-labelled occupancy would mark them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occvo_core.sim.roads import RoadGraph, Terrain

# Occ3D class ids used here (names in occvo_core.grid.CLASS_NAMES).
BARRIER, BICYCLE, BUS, CAR, CONSTRUCTION, MOTORCYCLE, PEDESTRIAN, CONE, TRAILER, TRUCK = 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
ROAD, OTHER_FLAT, SIDEWALK, TERRAIN, MANMADE, VEGETATION = 11, 12, 13, 14, 15, 16
NONE = 255  # empty object layer

RES = 0.2  # raster cell, metres
ZQ = 0.05  # object heights are stored in 5 cm steps (uint8: up to 12.75 m)
MIN_THIN = 0.25  # minimum half-width of thin structures (see module doc)

# Vehicle sizes: length, width, height, bottom clearance (m).
VEHICLE_SIZE = {
    CAR: (4.6, 1.9, 1.6, 0.25),
    TRUCK: (7.5, 2.5, 3.2, 0.35),
    BUS: (11.5, 2.6, 3.2, 0.35),
    TRAILER: (8.0, 2.5, 3.0, 0.5),
    CONSTRUCTION: (6.0, 2.6, 3.0, 0.3),
    MOTORCYCLE: (2.1, 0.8, 1.4, 0.2),
    BICYCLE: (1.8, 0.6, 1.2, 0.15),
    PEDESTRIAN: (0.6, 0.6, 1.75, 0.0),
}


def hash_uniform(seed: int, *keys, salt: int = 0) -> np.ndarray:
    """Uniform [0, 1) numbers from integer keys (splitmix64): stable per key whatever the raster bounds."""
    with np.errstate(over="ignore"):
        h = np.full(
            np.broadcast(*[np.asarray(k) for k in keys]).shape if keys else (),
            np.uint64(seed * 1000003 + salt),
            np.uint64,
        )
        for k in keys:
            h = h ^ (np.asarray(k).astype(np.int64).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15))
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


@dataclass
class Town:
    """The static world on a raster, plus what generated it."""

    seed: int
    origin: np.ndarray  # world x, y of cell (0,0)'s lower corner
    terrain: Terrain
    graph: RoadGraph
    h_base: np.ndarray  # (W,H) float32 terrain height at cell centres
    raise_cm: np.ndarray  # (W,H) uint8 ground top above terrain, cm
    ground: np.ndarray  # (W,H) uint8 ground class
    layers: np.ndarray  # (2,3,W,H) uint8: label, bottom, top (ZQ steps above terrain)
    parked: list = field(default_factory=list)  # (label, x, y, yaw) of parked vehicles

    @property
    def shape(self) -> tuple[int, int]:
        return self.ground.shape

    def nbytes(self) -> int:
        return self.h_base.nbytes + self.raise_cm.nbytes + self.ground.nbytes + self.layers.nbytes

    def ground_height(self, x, y) -> np.ndarray:
        """Terrain plus kerb raise at world x, y (nearest cell)."""
        u, v = self.cell(x, y)
        return self.terrain.height(x, y) + self.raise_cm[u, v] / 100.0

    def cell(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        u = np.clip(np.floor((np.asarray(x) - self.origin[0]) / RES).astype(int), 0, self.shape[0] - 1)
        v = np.clip(np.floor((np.asarray(y) - self.origin[1]) / RES).astype(int), 0, self.shape[1] - 1)
        return u, v


class Painter:
    """Writes discs and oriented boxes, trees and parked vehicles into the raster's object layers."""

    def __init__(self, town: Town):
        self.town = town

    def _window(self, x, y, reach):
        o, (w, h) = self.town.origin, self.town.shape
        u0, u1 = max(int((x - reach - o[0]) / RES), 0), min(int((x + reach - o[0]) / RES) + 1, w)
        v0, v1 = max(int((y - reach - o[1]) / RES), 0), min(int((y + reach - o[1]) / RES) + 1, h)
        if u0 >= u1 or v0 >= v1:
            return None
        cx = o[0] + (np.arange(u0, u1) + 0.5) * RES
        cy = o[1] + (np.arange(v0, v1) + 0.5) * RES
        return (slice(u0, u1), slice(v0, v1)), cx[:, None], cy[None, :]

    def _write(self, win, inside, layer, label, z0, z1):
        sl = win[0]
        base = self.town.raise_cm[sl][inside].astype(float) / 100.0  # objects stand on the kerb / lawn
        lay = self.town.layers[layer]
        lay[0][sl][inside] = label
        lay[1][sl][inside] = np.clip(np.round((base + z0) / ZQ), 0, 255).astype(np.uint8)
        lay[2][sl][inside] = np.clip(np.round((base + z1) / ZQ), 0, 255).astype(np.uint8)

    def disc(self, x, y, r, label, z0, z1, layer=0):
        r = max(r, MIN_THIN)
        win = self._window(x, y, r)
        if win is not None:
            self._write(win, (win[1] - x) ** 2 + (win[2] - y) ** 2 <= r * r, layer, label, z0, z1)

    def box(self, x, y, yaw, length, width, label, z0, z1, layer=0):
        hl, hw = max(length / 2, MIN_THIN), max(width / 2, MIN_THIN)
        win = self._window(x, y, np.hypot(hl, hw))
        if win is not None:
            c, s = np.cos(yaw), np.sin(yaw)
            dx, dy = win[1] - x, win[2] - y
            inside = (np.abs(c * dx + s * dy) <= hl) & (np.abs(-s * dx + c * dy) <= hw)
            self._write(win, inside, layer, label, z0, z1)

    def tree(self, rng: np.random.Generator, x: float, y: float) -> None:
        """A trunk (layer 0) under a crown (layer 1), sizes drawn from rng: three draws a tree."""
        crown = rng.uniform(1.4, 2.8)
        bottom = rng.uniform(1.8, 2.6)
        self.disc(x, y, 0.2, VEGETATION, 0.0, bottom + 0.4)
        self.disc(x, y, crown, VEGETATION, bottom, bottom + rng.uniform(2.5, 5.0), layer=1)

    def vehicle(self, label: int, x: float, y: float, yaw: float) -> None:
        """A parked vehicle's box, also listed in the town's parked vehicles."""
        length, width, height, clear = VEHICLE_SIZE[label]
        self.box(x, y, yaw, length, width, label, clear + 0.01, height)
        self.town.parked.append((label, float(x), float(y), float(yaw)))
