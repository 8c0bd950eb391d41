"""Street furniture along each side of the town's roads: lights, trees, signals and signs, shelters, barriers,
cones, and vehicles and bicycles parked at the kerb. Each side is sampled every metre; its hash decides what it gets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.sim.raster import (
    BARRIER,
    BICYCLE,
    BUS,
    CAR,
    CONE,
    MANMADE,
    MOTORCYCLE,
    NONE,
    ROAD,
    SIDEWALK,
    TRAILER,
    TRUCK,
    VEHICLE_SIZE,
    Painter,
    Town,
    hash_uniform,
)
from occvo_core.sim.roads import frames_along


@dataclass
class RoadSide:
    """One side of a road edge, sampled every metre (i indexes the samples): where its street furniture stands."""

    town: Town
    lower: np.ndarray
    upper: np.ndarray
    key: tuple[int, int]
    e_id: int
    sid: int  # 0: left of the edge's direction, 1: right
    sign: float  # -1.0 left, +1.0 right
    roll: float  # this side's hash in [0, 1): which furniture it gets, and where
    tree_lined: bool
    hw: float  # road half width
    sw: float  # sidewalk width
    pts: np.ndarray
    nrm: np.ndarray
    yaw: np.ndarray  # road direction at each sample

    def at(self, off: float, i: int) -> np.ndarray:
        """The point `off` m out from the centreline towards this side at sample i."""
        return self.pts[i] + self.sign * off * self.nrm[i]

    def free(self, p: np.ndarray, classes: tuple) -> bool:
        """p is inside the box, on one of these ground classes, and no object stands there yet."""
        t = self.town
        u, v = t.cell(p[0], p[1])
        inside = self.lower[0] < p[0] < self.upper[0] and self.lower[1] < p[1] < self.upper[1]
        return inside and t.ground[u, v] in classes and t.layers[0][0][u, v] == NONE


def road_sides(town: Town, edges: list, lower: np.ndarray, upper: np.ndarray):
    """Both sides of each road edge near the box that is at least 30 m long."""
    graph, seed = town.graph, town.seed
    for key in edges:
        e_id, hw, sw = graph.edge_ids[key], graph.half_width[key], graph.sidewalk[key]
        tree_lined = bool(hash_uniform(seed, e_id, salt=31) < 0.55)
        for sign in (-1.0, 1.0):
            sid = int(sign > 0)
            roll = float(hash_uniform(seed, e_id, sid, salt=32))
            _, pts, nrm, length = frames_along(graph.paths[key], 1.0)
            if length >= 30:
                yaw = np.arctan2(nrm[:, 0], -nrm[:, 1])
                yield RoadSide(town, lower, upper, key, e_id, sid, sign, roll, tree_lined, hw, sw, pts, nrm, yaw)


def street_lights(paint: Painter, side: RoadSide) -> None:
    """A light every 30 m at the sidewalk's road edge, its arm over the road."""
    for i in range(int(5 + 10 * side.roll), len(side.pts) - 5, 30):
        p = side.at(side.hw + 0.5, i)
        if side.free(p, (SIDEWALK,)):
            paint.disc(p[0], p[1], 0.15, MANMADE, 0.0, 7.5)
            q = side.at(side.hw - 0.6, i)
            paint.box(q[0], q[1], side.yaw[i] + np.pi / 2, 2.4, 0.3, MANMADE, 6.7, 7.1, layer=1)  # lamp arm


def street_trees(paint: Painter, rng: np.random.Generator, side: RoadSide) -> None:
    """On tree-lined roads, a tree every 8-14 m near the sidewalk's outer edge."""
    if side.tree_lined:
        for i in range(int(3 + 5 * side.roll), len(side.pts) - 3, int(8 + 6 * side.roll)):
            p = side.at(side.hw + side.sw - 0.9, i)
            if side.free(p, (SIDEWALK,)):
                paint.tree(rng, p[0], p[1])


def signals_and_signs(paint: Painter, side: RoadSide) -> None:
    """Before each intersection: traffic lights on the approach to most junctions of 3+ roads, else a sign."""
    a_node, b_node = side.key
    n = len(side.pts)
    for i, node in ((12, a_node), (n - 14, b_node)):
        if not 0 <= i < n:
            continue
        p = side.at(side.hw + 0.6, i)
        if not side.free(p, (SIDEWALK,)):
            continue
        approach = (side.sign < 0) == (node == b_node)  # the kerb on the right of traffic entering this node
        junction = len(side.town.graph.neighbours[node]) >= 3
        if approach and junction and hash_uniform(side.town.seed, node, salt=35) < 0.6:
            paint.disc(p[0], p[1], 0.12, MANMADE, 0.0, 5.2)  # signal mast
            q = side.at(side.hw - 2.0, i)
            paint.box(q[0], q[1], side.yaw[i] + np.pi / 2, 5.0, 0.25, MANMADE, 4.9, 5.2, layer=1)  # arm over the lane
            q = side.at(side.hw - 3.8, i)
            paint.box(q[0], q[1], side.yaw[i], 0.4, 0.4, MANMADE, 4.0, 4.9, layer=1)  # signal head
        else:
            paint.disc(p[0], p[1], 0.05, MANMADE, 0.0, 2.9)
            paint.box(p[0], p[1], side.yaw[i] + np.pi / 2, 0.8, 0.1, MANMADE, 2.0, 2.9, layer=1)


def bus_shelter(paint: Painter, side: RoadSide) -> None:
    """A bus shelter mid-block on one side in ten."""
    i = len(side.pts) // 2
    if 0.55 < side.roll < 0.65 and len(side.pts) > 40:
        p = side.at(side.hw + side.sw - 0.9, i)
        if side.free(p, (SIDEWALK,)):
            paint.box(p[0], p[1], side.yaw[i], 4.0, 1.3, MANMADE, 0.0, 2.6)


def kerb_barriers(paint: Painter, side: RoadSide) -> None:
    """A run of barriers along the kerb on one side in four."""
    if side.roll < 0.25:
        i0 = int(15 + side.roll * 60)
        for i in range(i0, min(i0 + 14, len(side.pts) - 15), 2):
            p = side.at(side.hw + 0.35, i)
            if side.free(p, (SIDEWALK,)):
                paint.box(p[0], p[1], side.yaw[i], 2.0, 0.5, BARRIER, 0.0, 0.9)


def edge_cones(paint: Painter, side: RoadSide) -> None:
    """A few cones at the road edge on about one side in seven."""
    if 0.25 < side.roll < 0.4:
        i0 = int(20 + (side.roll - 0.25) * 200)
        for i in range(i0, min(i0 + 8, len(side.pts) - 15), 2):
            p = side.at(side.hw - 0.4, i)
            if side.free(p, (ROAD,)):
                paint.disc(p[0], p[1], 0.2, CONE, 0.0, 0.7)


def lane_parking(paint: Painter, side: RoadSide) -> None:
    """On wide roads, vehicles parked in the parking lane with gaps, none near intersections."""
    if side.hw < 5.0:
        return
    seed, n, i = side.town.seed, len(side.pts), 14
    while i < n - 14:
        r = hash_uniform(seed, side.e_id, side.sid, i, salt=33)
        label = CAR if r < 0.78 else TRUCK if r < 0.86 else MOTORCYCLE if r < 0.93 else TRAILER if r < 0.96 else BUS
        length = VEHICLE_SIZE[label][0]
        if r < 0.62 or r > 0.78:  # else a free space
            c = side.at(side.hw - 1.15, i + int(length / 2))
            if side.free(c, (ROAD,)):
                paint.vehicle(label, c[0], c[1], side.yaw[i] if side.sign < 0 else side.yaw[i] + np.pi)
        i += int(length + 1.5 + 4 * hash_uniform(seed, side.e_id, side.sid, i, salt=34))


def sidewalk_bicycles(paint: Painter, side: RoadSide) -> None:
    """A row of bicycles parked across the sidewalk on one side in five."""
    if side.roll > 0.8:
        i0 = int(10 + 20 * (side.roll - 0.8))
        for i in range(i0, min(i0 + 5, len(side.pts) - 10)):
            p = side.at(side.hw + side.sw - 0.5, i)
            if side.free(p, (SIDEWALK,)):
                paint.vehicle(BICYCLE, p[0], p[1], side.yaw[i] + np.pi / 2)
