"""A seeded procedural town: road graph, ground classes, buildings, street furniture, parked vehicles.

build_town is the recipe: roads and sidewalks, city blocks of one kind each (buildings, parks, walled yards,
parking lots, construction sites) and what stands in them, then the street furniture along each road side
(occvo_core.sim.street). The town is painted on the raster of occvo_core.sim.raster.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from occvo_core.sim.raster import (
    BARRIER,
    CAR,
    CONE,
    CONSTRUCTION,
    MANMADE,
    NONE,
    OTHER_FLAT,
    RES,
    ROAD,
    SIDEWALK,
    TERRAIN,
    TRUCK,
    VEGETATION,
    ZQ,
    Painter,
    Town,
    hash_uniform,
)
from occvo_core.sim.roads import RoadGraph, Terrain, frames_along
from occvo_core.sim.street import (
    bus_shelter,
    edge_cones,
    kerb_barriers,
    lane_parking,
    road_sides,
    sidewalk_bicycles,
    signals_and_signs,
    street_lights,
    street_trees,
)

KERB_RAISE = {ROAD: 0.0, SIDEWALK: 0.15, TERRAIN: 0.1, OTHER_FLAT: 0.1}
LANE_OFFSET = 1.75  # right-hand traffic, centre of the right lane

# City block kinds and how often each occurs.
BLD, PARK, WALLED, PARKING, CONSTR = 1, 2, 3, 4, 5
BLOCK_KIND_P = np.array([0.5, 0.15, 0.12, 0.13, 0.10])


@dataclass
class _Frontage:
    """Per raster cell: the nearest road's edge id, arc length along it, distance behind its sidewalk, block kind."""

    eid: np.ndarray
    s: np.ndarray
    behind: np.ndarray  # m behind the sidewalk's outer edge (negative on roads and sidewalks)
    kind: np.ndarray  # BLD .. CONSTR, 0 on roads and sidewalks


class _Units(NamedTuple):
    """Per cell: the building unit along its road (12-25 m long) that the cell falls in."""

    depth: np.ndarray
    height: np.ndarray
    setback: np.ndarray  # per road edge
    in_gap: np.ndarray  # between this unit's building and the last


def build_town(seed: int, graph: RoadGraph, terrain: Terrain, lower: np.ndarray, upper: np.ndarray) -> Town:
    """Rasterise the town inside the world box [lower, upper] (x, y).

    The order is part of every scene: objects are placed where nothing stands yet and paint over what they
    overlap, and trees draw their sizes from rng one after another."""
    rng = np.random.default_rng([seed, 7])
    town = _bare_town(seed, graph, terrain, lower, upper)
    edges = _edges_near(graph, lower, upper)
    front = _paint_roads_and_sidewalks(town, edges)
    units = _building_units(seed, front)
    _paint_buildings(town, front, units)
    _paint_walled_yards(town, front, units)
    _paint_parking_lots(town, front)
    _paint_site_fences(town, front)
    _paint_park_hedges(town, front)
    _raise_kerbs(town)
    paint = Painter(town)
    _paint_block_objects(paint, rng, front, lower, upper)
    for side in road_sides(town, edges, lower, upper):  # street furniture
        street_lights(paint, side)
        street_trees(paint, rng, side)
        signals_and_signs(paint, side)
        bus_shelter(paint, side)
        kerb_barriers(paint, side)
        edge_cones(paint, side)
        lane_parking(paint, side)
        sidewalk_bicycles(paint, side)
    return town


def _cell_centres(origin: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    return origin[0] + (np.arange(w) + 0.5) * RES, origin[1] + (np.arange(h) + 0.5) * RES


def _bare_town(seed: int, graph: RoadGraph, terrain: Terrain, lower: np.ndarray, upper: np.ndarray) -> Town:
    """All terrain, no kerbs, empty object layers."""
    w, h = (np.ceil((upper - lower) / RES)).astype(int)
    origin = lower.astype(float)
    cx, cy = _cell_centres(origin, w, h)
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
    return town


def _edges_near(graph: RoadGraph, lower: np.ndarray, upper: np.ndarray, margin: float = 25.0) -> list:
    """The road edges whose polylines come within `margin` of the box."""
    return [
        key
        for key, poly in graph.paths.items()
        if not (
            poly[:, 0].max() < lower[0] - margin
            or poly[:, 0].min() > upper[0] + margin
            or poly[:, 1].max() < lower[1] - margin
            or poly[:, 1].min() > upper[1] + margin
        )
    ]


def _road_distance(town: Town, edges: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell: distance to the nearest road centreline (EDT), that road's edge id and arc length there."""
    (w, h), origin, graph = town.shape, town.origin, town.graph
    seed_id = np.full((w, h), -1, np.int32)
    seed_s = np.zeros((w, h), np.float32)
    for key in edges:
        s, pts, _, _ = frames_along(graph.paths[key], 0.1)
        u = np.floor((pts[:, 0] - origin[0]) / RES).astype(int)
        v = np.floor((pts[:, 1] - origin[1]) / RES).astype(int)
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        seed_id[u[ok], v[ok]] = graph.edge_ids[key]
        seed_s[u[ok], v[ok]] = s[ok]
    if not (seed_id >= 0).any():  # no road inside: all terrain
        return np.full((w, h), 1e9), np.full((w, h), -1), np.zeros((w, h))
    dist, (iu, iv) = ndimage.distance_transform_edt(seed_id < 0, sampling=RES, return_indices=True)
    return dist, seed_id[iu, iv], seed_s[iu, iv]


def _paint_roads_and_sidewalks(town: Town, edges: list) -> _Frontage:
    """Road and sidewalk ground within each edge's widths; the rest splits into city blocks."""
    graph = town.graph
    dist, eid, s_near = _road_distance(town, edges)
    hw_of = np.zeros(len(graph.edge_ids) + 1, np.float32)
    sw_of = np.zeros(len(graph.edge_ids) + 1, np.float32)
    for k, e in graph.edge_ids.items():
        hw_of[e], sw_of[e] = graph.half_width[k], graph.sidewalk[k]
    hw, sw = hw_of[eid], sw_of[eid]
    road = dist <= hw
    walk = ~road & (dist <= hw + sw)
    town.ground[road] = ROAD
    town.ground[walk] = SIDEWALK
    return _Frontage(eid, s_near, dist - hw - sw, _block_kinds(town, ~road & ~walk))


def _block_kinds(town: Town, free: np.ndarray) -> np.ndarray:
    """City blocks: connected areas behind the sidewalks, each of one kind (hashed from its first cell's 50 m tile)."""
    blocks, n_blocks = ndimage.label(free)
    block_kind = np.zeros(n_blocks + 1, np.int8)
    if n_blocks:
        cx, cy = _cell_centres(town.origin, *town.shape)
        first = ndimage.minimum_position(blocks, blocks, index=np.arange(1, n_blocks + 1))
        for b, (u, v) in enumerate(first, start=1):
            r = hash_uniform(town.seed, int(cx[u] // 50), int(cy[v] // 50), salt=11)
            block_kind[b] = 1 + min(int(np.searchsorted(np.cumsum(BLOCK_KIND_P), r)), len(BLOCK_KIND_P) - 1)
    return block_kind[blocks]


def _building_units(seed: int, front: _Frontage) -> _Units:
    """Units of 12-25 m along each road, each of its own depth, height and gap; one setback a road."""
    unit_len = 12.0 + 13.0 * hash_uniform(seed, front.eid, salt=1)
    unit = np.floor(front.s / unit_len).astype(np.int64)
    u_gap = 4.0 * hash_uniform(seed, front.eid, unit, salt=2) ** 2
    u_depth = 8.0 + 10.0 * hash_uniform(seed, front.eid, unit, salt=3)
    u_height = 4.5 + 9.5 * hash_uniform(seed, front.eid, unit, salt=4)
    setback = 2.5 * hash_uniform(seed, front.eid, salt=5)
    return _Units(u_depth, u_height, setback, (front.s - unit * unit_len) < u_gap)


def _fill(town: Town, mask: np.ndarray, label: int, z0, z1) -> None:
    """Object layer 0 over a cell mask; z0, z1 scalars or per-cell arrays (m above terrain)."""
    lay = town.layers[0]
    lay[0][mask] = label
    for z, row in ((z0, lay[1]), (z1, lay[2])):
        row[mask] = np.clip(np.round((np.asarray(z) if np.ndim(z) == 0 else z[mask]) / ZQ), 0, 255).astype(np.uint8)


def _paint_buildings(town: Town, front: _Frontage, units: _Units) -> None:
    """Building blocks: a paved forecourt, then facades unit by unit, lawn behind and in the gaps."""
    bld, e, setback = front.kind == BLD, front.behind, units.setback
    town.ground[bld & (e > 0) & (e < setback)] = OTHER_FLAT
    facade = bld & (e >= setback) & (e <= setback + units.depth) & ~units.in_gap
    _fill(town, facade, MANMADE, 0.0, units.height)
    town.ground[bld & ~facade & (e >= setback)] = TERRAIN


def _paint_walled_yards(town: Town, front: _Frontage, units: _Units) -> None:
    """A wall with gates every 40 m along the sidewalk, buildings 9 m behind it."""
    walled, e = front.kind == WALLED, front.behind
    wall_h = 1.6 + 0.9 * hash_uniform(town.seed, front.eid, salt=6)
    gate = (front.s % 40.0) < 4.0
    _fill(town, walled & (e > 0.3) & (e < 0.8) & ~gate, MANMADE, 0.0, wall_h)
    _fill(town, walled & (e > 9.0) & (e < 9.0 + units.depth) & ~units.in_gap, MANMADE, 0.0, units.height)


def _paint_parking_lots(town: Town, front: _Frontage) -> None:
    """Parking lots are road surface: nuScenes labels them driveable."""
    town.ground[(front.kind == PARKING) & (front.behind > 0.0)] = ROAD


def _paint_site_fences(town: Town, front: _Frontage) -> None:
    """Construction sites: barriers along the sidewalk with a gap every 6 m."""
    e = front.behind
    _fill(town, (front.kind == CONSTR) & (e > 0.3) & (e < 0.9) & ((front.s % 6.0) > 0.6), BARRIER, 0.0, 1.0)


def _paint_park_hedges(town: Town, front: _Frontage) -> None:
    """Parks: a hedge behind the sidewalk, open every 15 m."""
    e = front.behind
    _fill(town, (front.kind == PARK) & (e > 0.6) & (e < 1.6) & ((front.s % 15.0) > 3.0), VEGETATION, 0.0, 1.1)


def _raise_kerbs(town: Town) -> None:
    """Sidewalks, lawns and forecourts stand above the road by their kerb."""
    for label, r in KERB_RAISE.items():
        town.raise_cm[town.ground == label] = int(round(r * 100))


def _block_lattice(town: Town, lower: np.ndarray, upper: np.ndarray, g: float = 7.0):
    """Candidate points on a jittered `g` m lattice inside the box: (x, y, roll in [0, 1), u, v) each."""
    gx0, gy0 = np.floor(lower / g).astype(int)
    gx1, gy1 = np.ceil(upper / g).astype(int)
    ii, jj = np.meshgrid(np.arange(gx0, gx1), np.arange(gy0, gy1), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    px = (ii + 0.2 + 0.6 * hash_uniform(town.seed, ii, jj, salt=21)) * g
    py = (jj + 0.2 + 0.6 * hash_uniform(town.seed, ii, jj, salt=22)) * g
    roll = hash_uniform(town.seed, ii, jj, salt=23)
    pu, pv = town.cell(px, py)
    inside = (px > lower[0]) & (px < upper[0]) & (py > lower[1]) & (py < upper[1])
    return zip(px[inside], py[inside], roll[inside], pu[inside], pv[inside])


def _paint_block_objects(
    paint: Painter, rng: np.random.Generator, front: _Frontage, lower: np.ndarray, upper: np.ndarray
) -> None:
    """Loose objects inside blocks: trees in parks, courtyards and walled yards; parked cars and lights in lots;
    machines, cones and cabins on construction sites."""
    town = paint.town
    for x, y, r, u, v in _block_lattice(town, lower, upper):
        kind, depth = front.kind[u, v], front.behind[u, v]
        if town.layers[0][0][u, v] != NONE or town.ground[u, v] in (SIDEWALK,) or depth < 2.0:
            continue
        if kind in (PARK, WALLED, BLD) and r < (0.75 if kind == PARK else 0.35):
            paint.tree(rng, x, y)
        elif kind == PARKING and depth > 3.0 and r < 0.7:
            yaw = 0.0 if hash_uniform(town.seed, u, salt=24) < 0.5 else np.pi / 2
            paint.vehicle(CAR if r < 0.6 else TRUCK, x, y, yaw)
        elif kind == CONSTR:
            if r < 0.15:
                paint.vehicle(CONSTRUCTION, x, y, r * 40.0)
            elif r < 0.5:
                for c in range(3):
                    paint.disc(x + 1.2 * c, y, 0.2, CONE, 0.0, 0.7)
            elif r < 0.6:
                paint.box(x, y, 0.0, 5.0, 3.0, MANMADE, 0.0, 2.6)  # site cabin
        elif kind == PARKING and r > 0.9:
            paint.disc(x, y, 0.15, MANMADE, 0.0, 7.0)  # lot light
