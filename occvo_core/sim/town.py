"""A seeded procedural town: road graph, ground classes, buildings, street furniture, parked vehicles.

The world is stored 2.5-D on a 0.2 m raster (small and fast to sample): per cell a ground class and kerb
raise, and two object layers (label, bottom, top) so a tree crown can hang over its trunk or a parked car.
Heights are relative to a gently rolling terrain h(x, y), which gives the ego real pitch, roll and z motion.
Thin things (poles, cones, sign plates, trunks) are drawn at least 0.5 m wide so that the 0.4 m
occupancy voxels they cross are occupied, as a lidar-labelled occupancy would mark them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from occvo_core.sim.roads import RoadGraph, Terrain, frames_along

# Occ3D class ids used here (names in occvo_core.grid.CLASS_NAMES).
BARRIER, BICYCLE, BUS, CAR, CONSTRUCTION, MOTORCYCLE, PEDESTRIAN, CONE, TRAILER, TRUCK = 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
ROAD, OTHER_FLAT, SIDEWALK, TERRAIN, MANMADE, VEGETATION = 11, 12, 13, 14, 15, 16
NONE = 255  # empty object layer

RES = 0.2  # raster cell, metres
ZQ = 0.05  # object heights are stored in 5 cm steps (uint8: up to 12.75 m)
KERB_RAISE = {ROAD: 0.0, SIDEWALK: 0.15, TERRAIN: 0.1, OTHER_FLAT: 0.1}
LANE_OFFSET = 1.75  # right-hand traffic, centre of the right lane
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


class _Painter:
    """Writes discs and oriented boxes into the raster's object layers."""

    def __init__(self, town: Town):
        self.t = town

    def _window(self, x, y, reach):
        o, (w, h) = self.t.origin, self.t.shape
        u0, u1 = max(int((x - reach - o[0]) / RES), 0), min(int((x + reach - o[0]) / RES) + 1, w)
        v0, v1 = max(int((y - reach - o[1]) / RES), 0), min(int((y + reach - o[1]) / RES) + 1, h)
        if u0 >= u1 or v0 >= v1:
            return None
        cx = o[0] + (np.arange(u0, u1) + 0.5) * RES
        cy = o[1] + (np.arange(v0, v1) + 0.5) * RES
        return (slice(u0, u1), slice(v0, v1)), cx[:, None], cy[None, :]

    def _write(self, win, inside, layer, label, z0, z1):
        sl = win[0]
        base = self.t.raise_cm[sl][inside].astype(float) / 100.0  # objects stand on the kerb / lawn
        lay = self.t.layers[layer]
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


def build_town(seed: int, graph: RoadGraph, terrain: Terrain, lower: np.ndarray, upper: np.ndarray) -> Town:
    """Rasterise the town inside the world box [lower, upper] (x, y)."""
    rng = np.random.default_rng([seed, 7])
    w, h = (np.ceil((upper - lower) / RES)).astype(int)
    origin = lower.astype(float)
    cx = origin[0] + (np.arange(w) + 0.5) * RES
    cy = origin[1] + (np.arange(h) + 0.5) * RES
    town = Town(
        seed,
        origin,
        terrain,
        graph,
        terrain.height(cx[:, None], cy[None, :]).astype(np.float32),
        np.zeros((w, h), np.uint8),
        np.full((w, h), TERRAIN, np.uint8),
        np.zeros((2, 3, w, h), np.uint8),
    )
    town.layers[:, 0] = NONE

    # Road centrelines -> nearest-road distance field (EDT), edge id and arc length per cell.
    margin = 25.0
    seed_id = np.full((w, h), -1, np.int32)
    seed_s = np.zeros((w, h), np.float32)
    edges = []
    for key, poly in graph.paths.items():
        if (
            poly[:, 0].max() < lower[0] - margin
            or poly[:, 0].min() > upper[0] + margin
            or poly[:, 1].max() < lower[1] - margin
            or poly[:, 1].min() > upper[1] + margin
        ):
            continue
        edges.append(key)
        s, pts, _, _ = frames_along(poly, 0.1)
        u = np.floor((pts[:, 0] - origin[0]) / RES).astype(int)
        v = np.floor((pts[:, 1] - origin[1]) / RES).astype(int)
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        seed_id[u[ok], v[ok]] = graph.edge_ids[key]
        seed_s[u[ok], v[ok]] = s[ok]
    if (seed_id >= 0).any():
        dist, (iu, iv) = ndimage.distance_transform_edt(seed_id < 0, sampling=RES, return_indices=True)
        eid = seed_id[iu, iv]
        s_near = seed_s[iu, iv]
    else:  # no road inside: all terrain
        dist, eid, s_near = np.full((w, h), 1e9), np.full((w, h), -1), np.zeros((w, h))
    hw_of = np.zeros(len(graph.edge_ids) + 1, np.float32)
    sw_of = np.zeros(len(graph.edge_ids) + 1, np.float32)
    for k, e in graph.edge_ids.items():
        hw_of[e], sw_of[e] = graph.half_width[k], graph.sidewalk[k]
    hw, sw = hw_of[eid], sw_of[eid]
    road = dist <= hw
    walk = ~road & (dist <= hw + sw)
    town.ground[road] = ROAD
    town.ground[walk] = SIDEWALK
    e = dist - hw - sw  # distance behind the sidewalk's outer edge

    # City blocks: connected areas behind the sidewalks, each of one kind.
    blocks, n_blocks = ndimage.label(~road & ~walk)
    kind_p = np.array([0.5, 0.15, 0.12, 0.13, 0.10])
    block_kind = np.zeros(n_blocks + 1, np.int8)
    if n_blocks:
        first = ndimage.minimum_position(blocks, blocks, index=np.arange(1, n_blocks + 1))
        for b, (u, v) in enumerate(first, start=1):
            r = hash_uniform(seed, int(cx[u] // 50), int(cy[v] // 50), salt=11)
            block_kind[b] = 1 + min(int(np.searchsorted(np.cumsum(kind_p), r)), len(kind_p) - 1)
    kind_cell = block_kind[blocks]
    BLD, PARK, WALLED, PARKING, CONSTR = 1, 2, 3, 4, 5

    unit_len = 12.0 + 13.0 * hash_uniform(seed, eid, salt=1)
    unit = np.floor(s_near / unit_len).astype(np.int64)
    u_gap = 4.0 * hash_uniform(seed, eid, unit, salt=2) ** 2
    u_depth = 8.0 + 10.0 * hash_uniform(seed, eid, unit, salt=3)
    u_height = 4.5 + 9.5 * hash_uniform(seed, eid, unit, salt=4)
    setback = 2.5 * hash_uniform(seed, eid, salt=5)
    in_gap = (s_near - unit * unit_len) < u_gap
    lay = town.layers[0]

    def put(mask, label, z0, z1):
        lay[0][mask] = label
        lay[1][mask] = (
            np.clip(np.round(np.asarray(z0) / ZQ), 0, 255).astype(np.uint8)
            if np.ndim(z0) == 0
            else np.clip(np.round(z0[mask] / ZQ), 0, 255).astype(np.uint8)
        )
        lay[2][mask] = (
            np.clip(np.round(np.asarray(z1) / ZQ), 0, 255).astype(np.uint8)
            if np.ndim(z1) == 0
            else np.clip(np.round(z1[mask] / ZQ), 0, 255).astype(np.uint8)
        )

    bld = kind_cell == BLD
    front = bld & (e > 0) & (e < setback)
    town.ground[front] = OTHER_FLAT  # forecourts
    facade = bld & (e >= setback) & (e <= setback + u_depth) & ~in_gap
    put(facade, MANMADE, 0.0, u_height)
    town.ground[bld & ~facade & (e >= setback)] = TERRAIN

    walled = kind_cell == WALLED
    wall_h = 1.6 + 0.9 * hash_uniform(seed, eid, salt=6)
    gate = (s_near % 40.0) < 4.0
    put(walled & (e > 0.3) & (e < 0.8) & ~gate, MANMADE, 0.0, wall_h)
    put(walled & (e > 9.0) & (e < 9.0 + u_depth) & ~in_gap, MANMADE, 0.0, u_height)

    parking = kind_cell == PARKING
    town.ground[parking & (e > 0.0)] = ROAD  # nuScenes labels parking lots driveable

    constr = kind_cell == CONSTR
    put(constr & (e > 0.3) & (e < 0.9) & ((s_near % 6.0) > 0.6), BARRIER, 0.0, 1.0)

    park = kind_cell == PARK
    hedge = park & (e > 0.6) & (e < 1.6) & ((s_near % 15.0) > 3.0)
    put(hedge, VEGETATION, 0.0, 1.1)

    for label, r in KERB_RAISE.items():
        town.raise_cm[town.ground == label] = int(round(r * 100))
    paint = _Painter(town)

    # Loose objects inside blocks: trees in parks, courtyards and walled yards; parked cars in lots;
    # machines and cones on construction sites. Candidate points on a jittered 7 m lattice.
    g = 7.0
    gx0, gy0 = np.floor(lower / g).astype(int)
    gx1, gy1 = np.ceil(upper / g).astype(int)
    ii, jj = np.meshgrid(np.arange(gx0, gx1), np.arange(gy0, gy1), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    px = (ii + 0.2 + 0.6 * hash_uniform(seed, ii, jj, salt=21)) * g
    py = (jj + 0.2 + 0.6 * hash_uniform(seed, ii, jj, salt=22)) * g
    roll = hash_uniform(seed, ii, jj, salt=23)
    pu, pv = town.cell(px, py)
    inside = (px > lower[0]) & (px < upper[0]) & (py > lower[1]) & (py < upper[1])
    for x, y, r, u, v in zip(px[inside], py[inside], roll[inside], pu[inside], pv[inside]):
        kind, depth = kind_cell[u, v], e[u, v]
        if lay[0][u, v] != NONE or town.ground[u, v] in (SIDEWALK,) or depth < 2.0:
            continue
        if kind in (PARK, WALLED, BLD) and r < (0.75 if kind == PARK else 0.35):
            _tree(paint, rng, x, y)
        elif kind == PARKING and depth > 3.0 and r < 0.7:
            yaw = 0.0 if hash_uniform(seed, u, salt=24) < 0.5 else np.pi / 2
            _vehicle(paint, town, CAR if r < 0.6 else TRUCK, x, y, yaw)
        elif kind == CONSTR:
            if r < 0.15:
                _vehicle(paint, town, CONSTRUCTION, x, y, r * 40.0)
            elif r < 0.5:
                for c in range(3):
                    paint.disc(x + 1.2 * c, y, 0.2, CONE, 0.0, 0.7)
            elif r < 0.6:
                paint.box(x, y, 0.0, 5.0, 3.0, MANMADE, 0.0, 2.6)  # site cabin
        elif kind == PARKING and r > 0.9:
            paint.disc(x, y, 0.15, MANMADE, 0.0, 7.0)  # lot light

    # Street furniture along each road side.
    for key in edges:
        poly = graph.paths[key]
        e_id, hw_e, sw_e = graph.edge_ids[key], graph.half_width[key], graph.sidewalk[key]
        tree_lined = hash_uniform(seed, e_id, salt=31) < 0.55
        for side in (-1.0, 1.0):
            sid = int(side > 0)
            r_side = hash_uniform(seed, e_id, sid, salt=32)
            s, pts, nrm, length = frames_along(poly, 1.0)
            if length < 30:
                continue

            def at(off, i):  # called within this iteration only
                return pts[i] + side * off * nrm[i]  # noqa: B023

            def on(p, classes):
                u, v = town.cell(p[0], p[1])
                inside_ = lower[0] < p[0] < upper[0] and lower[1] < p[1] < upper[1]
                return inside_ and town.ground[u, v] in classes and lay[0][u, v] == NONE

            yaw_of = np.arctan2(nrm[:, 0], -nrm[:, 1])  # road direction
            for i in range(int(5 + 10 * r_side), len(s) - 5, 30):  # street lights
                p = at(hw_e + 0.5, i)
                if on(p, (SIDEWALK,)):
                    paint.disc(p[0], p[1], 0.15, MANMADE, 0.0, 7.5)
                    q = at(hw_e - 0.6, i)
                    paint.box(q[0], q[1], yaw_of[i] + np.pi / 2, 2.4, 0.3, MANMADE, 6.7, 7.1, layer=1)  # lamp arm
            if tree_lined:
                step = int(8 + 6 * r_side)
                for i in range(int(3 + 5 * r_side), len(s) - 3, step):
                    p = at(hw_e + sw_e - 0.9, i)
                    if on(p, (SIDEWALK,)):
                        _tree(paint, rng, p[0], p[1])
            a_node, b_node = key
            for i, node in ((12, a_node), (len(s) - 14, b_node)):  # before intersections: traffic lights or signs
                if not 0 <= i < len(s):
                    continue
                p = at(hw_e + 0.6, i)
                if not on(p, (SIDEWALK,)):
                    continue
                approach = (side < 0) == (node == b_node)  # the kerb on the right of traffic entering this node
                if approach and len(graph.neighbours[node]) >= 3 and hash_uniform(seed, node, salt=35) < 0.6:
                    paint.disc(p[0], p[1], 0.12, MANMADE, 0.0, 5.2)  # signal mast
                    q = at(hw_e - 2.0, i)
                    paint.box(
                        q[0], q[1], yaw_of[i] + np.pi / 2, 5.0, 0.25, MANMADE, 4.9, 5.2, layer=1
                    )  # arm over the lane
                    q = at(hw_e - 3.8, i)
                    paint.box(q[0], q[1], yaw_of[i], 0.4, 0.4, MANMADE, 4.0, 4.9, layer=1)  # signal head
                else:
                    paint.disc(p[0], p[1], 0.05, MANMADE, 0.0, 2.9)
                    paint.box(p[0], p[1], yaw_of[i] + np.pi / 2, 0.8, 0.1, MANMADE, 2.0, 2.9, layer=1)
            if 0.55 < r_side < 0.65 and len(s) > 40:  # a bus shelter mid-block
                i = len(s) // 2
                p = at(hw_e + sw_e - 0.9, i)
                if on(p, (SIDEWALK,)):
                    paint.box(p[0], p[1], yaw_of[i], 4.0, 1.3, MANMADE, 0.0, 2.6)
            if r_side < 0.25:  # a run of barriers along the kerb
                i0 = int(15 + r_side * 60)
                for i in range(i0, min(i0 + 14, len(s) - 15), 2):
                    p = at(hw_e + 0.35, i)
                    if on(p, (SIDEWALK,)):
                        paint.box(p[0], p[1], yaw_of[i], 2.0, 0.5, BARRIER, 0.0, 0.9)
            if 0.25 < r_side < 0.4:  # cones at the road edge
                i0 = int(20 + (r_side - 0.25) * 200)
                for i in range(i0, min(i0 + 8, len(s) - 15), 2):
                    p = at(hw_e - 0.4, i)
                    if on(p, (ROAD,)):
                        paint.disc(p[0], p[1], 0.2, CONE, 0.0, 0.7)
            if hw_e >= 5.0:  # parked vehicles in the parking lane, not near intersections
                i = 14
                while i < len(s) - 14:
                    r = hash_uniform(seed, e_id, sid, i, salt=33)
                    cls_ = (
                        CAR
                        if r < 0.78
                        else TRUCK
                        if r < 0.86
                        else MOTORCYCLE
                        if r < 0.93
                        else TRAILER
                        if r < 0.96
                        else BUS
                    )
                    length_ = VEHICLE_SIZE[cls_][0]
                    if r < 0.62 or r > 0.78:
                        c = at(hw_e - 1.15, i + int(length_ / 2))
                        if on(c, (ROAD,)):
                            yaw = yaw_of[i] if side < 0 else yaw_of[i] + np.pi
                            _vehicle(paint, town, cls_, c[0], c[1], yaw)
                    i += int(length_ + 1.5 + 4 * hash_uniform(seed, e_id, sid, i, salt=34))
            if r_side > 0.8:  # bicycles parked on the sidewalk
                i0 = int(10 + 20 * (r_side - 0.8))
                for i in range(i0, min(i0 + 5, len(s) - 10)):
                    p = at(hw_e + sw_e - 0.5, i)
                    if on(p, (SIDEWALK,)):
                        _vehicle(paint, town, BICYCLE, p[0], p[1], yaw_of[i] + np.pi / 2)
    return town


def _tree(paint: _Painter, rng: np.random.Generator, x: float, y: float) -> None:
    crown = rng.uniform(1.4, 2.8)
    bottom = rng.uniform(1.8, 2.6)
    paint.disc(x, y, 0.2, VEGETATION, 0.0, bottom + 0.4)
    paint.disc(x, y, crown, VEGETATION, bottom, bottom + rng.uniform(2.5, 5.0), layer=1)


def _vehicle(paint: _Painter, town: Town, label: int, x: float, y: float, yaw: float) -> None:
    length, width, height, clear = VEHICLE_SIZE[label]
    paint.box(x, y, yaw, length, width, label, clear + 0.01, height)
    town.parked.append((label, float(x), float(y), float(yaw)))
