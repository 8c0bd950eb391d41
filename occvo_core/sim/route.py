"""Paths through the road graph and time-parametrised motion along them.

A path is a lane-offset polyline (right-hand traffic) through a node sequence, with turns rounded by
smoothing. Speed follows a profile limited by cruise speed, lateral acceleration in curves, and stops
at intersections, with bounded acceleration and braking; the time at each arc length follows from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import gaussian_filter1d

from occvo_core.sim.roads import RoadGraph
from occvo_core.sim.town import LANE_OFFSET

DS = 0.2  # arc-length step of the motion tables, m


def resample(poly: np.ndarray, step: float) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.arange(0.0, cum[-1], step)
    return np.column_stack([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])])


def random_walk(
    graph: RoadGraph, rng: np.random.Generator, start: int, prev: int, length: float, force_turn_first: bool = False
) -> list[int]:
    """Nodes from prev -> start onwards, never turning back, until the path is at least `length` long."""
    nodes, total = [prev, start], 0.0
    while total < length:
        a, b = nodes[-2], nodes[-1]
        options = [n for n in graph.neighbours[b] if n != a]
        if not options:
            options = [a]
        d_in = graph.nodes[b] - graph.nodes[a]
        if force_turn_first and len(nodes) == 2:
            turning = [n for n in options if _angle(d_in, graph.nodes[n] - graph.nodes[b]) > np.pi / 4]
            options = turning or options
        nxt = options[rng.integers(len(options))]
        total += float(np.sum(np.linalg.norm(np.diff(graph.path(b, nxt), axis=0), axis=1)))
        nodes.append(nxt)
    return nodes


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1)))


@dataclass
class Path:
    """A smoothed lane path: xy (K,2) at DS steps, heading (K,), curvature (K,), node arc lengths."""

    xy: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    node_s: np.ndarray  # arc length at which the path passes each interior node
    node_hw: np.ndarray  # half width of the road crossed there

    @property
    def s(self) -> np.ndarray:
        return np.arange(len(self.xy)) * DS

    @property
    def length(self) -> float:
        return (len(self.xy) - 1) * DS


def _offset(poly: np.ndarray, offset: float) -> np.ndarray:
    tangent = np.gradient(poly, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return poly + offset * np.column_stack([tangent[:, 1], -tangent[:, 0]])  # right of the centreline


def _trim(poly: np.ndarray, start: float, end: float) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.linspace(start, cum[-1] - end, max(int((cum[-1] - end - start) / 0.5), 2) + 1)
    return np.column_stack([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])])


def _connector(p0: np.ndarray, d0: np.ndarray, p3: np.ndarray, d3: np.ndarray) -> np.ndarray:
    """Cubic Bezier from p0 (heading d0) to p3 (heading d3) approximating a circular arc through the turn."""
    cross = d0[0] * d3[1] - d0[1] * d3[0]
    theta = abs(np.arctan2(cross, np.dot(d0, d3)))
    chord = float(np.linalg.norm(p3 - p0))
    if theta < 0.05 or abs(cross) < 1e-6:
        h0 = h3 = chord / 3
    else:  # tangent lines meet at p0 + t d0 = p3 - u d3
        t, u = np.linalg.solve(np.column_stack([d0, d3]), p3 - p0)
        k = (4 / 3) * np.tan(theta / 4) / np.tan(theta / 2)
        h0, h3 = max(t, 1.0) * k, max(u, 1.0) * k
    b = np.linspace(0, 1, max(int(chord / 0.25), 4))[:, None]
    c0, c1, c2 = p0, p0 + h0 * d0, p3 - h3 * d3
    return (1 - b) ** 3 * c0 + 3 * (1 - b) ** 2 * b * c1 + 3 * (1 - b) * b**2 * c2 + b**3 * p3


def lane_path(graph: RoadGraph, nodes: list[int], offset: float = LANE_OFFSET, corner_m: float = 12.0) -> Path:
    """The right lane through `nodes`: each road's lane stops `corner_m` before an intersection and a smooth
    curve (about a circular arc: ~10 m radius for right turns, ~14 m for left) joins it to the next road's lane."""
    lanes = []
    for i, (a, b) in enumerate(zip(nodes[:-1], nodes[1:])):
        lane = _offset(graph.path(a, b), offset)
        lanes.append(_trim(lane, corner_m if i > 0 else 0.0, corner_m if i < len(nodes) - 2 else 0.0))

    def length(p):
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

    pieces, node_s, node_hw, total = [lanes[0]], [], [], length(lanes[0])
    for prev, nxt, (a, b) in zip(lanes[:-1], lanes[1:], zip(nodes[:-1], nodes[1:])):
        d0 = prev[-1] - prev[-2]
        d3 = nxt[1] - nxt[0]
        conn = _connector(prev[-1], d0 / np.linalg.norm(d0), nxt[0], d3 / np.linalg.norm(d3))
        pieces += [conn[1:], nxt[1:]]
        node_s.append(total + length(conn) / 2)  # where the path passes the intersection
        node_hw.append(graph.half_width[graph.key(a, b)])
        total += length(conn) + length(nxt)
    poly = resample(np.concatenate(pieces), DS)
    # steering takes time: smoothing ramps the curvature in and out over a few metres, as clothoids do
    poly = gaussian_filter1d(poly, 2.5 / DS, axis=0, mode="nearest")
    d = np.gradient(poly, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    heading = gaussian_filter1d(heading, 2.0, mode="nearest")
    curvature = np.gradient(heading) / DS
    return Path(poly, heading, curvature, np.array(node_s), np.array(node_hw))


@dataclass
class Motion:
    """Arc length as a function of time along a Path."""

    path: Path
    t_knots: np.ndarray
    s_knots: np.ndarray
    v_knots: np.ndarray

    def s_at(self, t) -> np.ndarray:
        return np.interp(t, self.t_knots, self.s_knots)

    def speed_at(self, t) -> np.ndarray:
        return np.interp(t, self.t_knots, self.v_knots)

    def xy_heading(self, t) -> tuple[np.ndarray, np.ndarray]:
        s = self.s_at(t)
        k = np.clip(s / DS, 0, len(self.path.xy) - 1)
        x = np.interp(k, np.arange(len(self.path.xy)), self.path.xy[:, 0])
        y = np.interp(k, np.arange(len(self.path.xy)), self.path.xy[:, 1])
        return np.column_stack([x, y]), np.interp(k, np.arange(len(self.path.xy)), self.path.heading)


@njit(cache=True)
def _limit_accelerations(lim, v0, acc_ds, brake_ds):
    v = lim.copy()
    v[0] = v0
    for k in range(1, len(v)):
        v[k] = min(v[k], math.sqrt(v[k - 1] ** 2 + 2 * acc_ds))
    for k in range(len(v) - 2, -1, -1):
        v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2 * brake_ds))
    return v


def speed_profile(
    path: Path,
    v_cruise: np.ndarray,
    v0: float,
    stops: list[tuple[float, float]] = (),
    a_acc: float = 1.6,
    a_brake: float = 2.5,
    a_lat: float = 2.0,
    v_max: float = 15.0,
) -> Motion:
    """v_cruise: cruise speed per path sample; stops: (arc length, dwell s). Returns the time tables."""
    n = len(path.xy)
    lim = np.minimum(np.minimum(v_cruise, v_max), np.sqrt(a_lat / np.maximum(np.abs(path.curvature), 1e-6)))
    lim[0] = min(lim[0], v0)
    stop_idx = {}
    for s_stop, dwell in stops:
        k = int(round(s_stop / DS))
        if 0 < k < n - 1:
            lim[k] = 0.0
            stop_idx[k] = dwell
    v = _limit_accelerations(lim, min(v0, lim[0]), a_acc * DS, a_brake * DS)
    dt = 2 * DS / np.maximum(v[:-1] + v[1:], 1e-6)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    s = np.arange(n) * DS
    t_k, s_k, v_k = list(t), list(s), list(v)
    for k in sorted(stop_idx, reverse=True):  # standing still: two knots at the same arc length
        t_k.insert(k + 1, t[k] + stop_idx[k])
        s_k.insert(k + 1, s[k])
        v_k.insert(k + 1, 0.0)
        for j in range(k + 2, len(t_k)):
            t_k[j] += stop_idx[k]
    return Motion(path, np.array(t_k), np.array(s_k), np.array(v_k))


def block_loop(graph: RoadGraph, rng: np.random.Generator, blocks: tuple[int, int]) -> list[int]:
    """A closed circuit around a rectangle of `blocks` (nx, ny) city blocks near the origin: its boundary nodes
    in driving order (the first node not repeated at the end). The graph is RoadGraph.random's square lattice
    (node (i, j) = i * side + j); the rectangle nearest the origin whose boundary roads all exist is taken."""
    side = int(round(np.sqrt(len(graph.nodes))))
    a, b = int(blocks[0]), int(blocks[1])
    if side * side != len(graph.nodes) or a < 1 or b < 1 or a >= side or b >= side:
        raise ValueError(f"no {a}x{b} block loop in a graph of {len(graph.nodes)} nodes")
    candidates = []
    for i0 in range(side - a):
        for j0 in range(side - b):
            ring = (
                [(i, j0) for i in range(i0, i0 + a)]
                + [(i0 + a, j) for j in range(j0, j0 + b)]
                + [(i, j0 + b) for i in range(i0 + a, i0, -1)]
                + [(i0, j) for j in range(j0 + b, j0, -1)]
            )
            nodes = [i * side + j for i, j in ring]
            if all(n in graph.neighbours[m] for m, n in zip(nodes, nodes[1:] + nodes[:1])):
                centre = graph.nodes[nodes].mean(axis=0)
                candidates.append((float(np.linalg.norm(centre)), nodes))
    if not candidates:
        raise ValueError(f"no {a}x{b} block loop with all its roads in this graph")
    nodes = min(candidates, key=lambda c: c[0])[1]
    if rng.random() < 0.5:  # either way round the blocks
        nodes = nodes[::-1]
    k = int(rng.integers(len(nodes)))
    return nodes[k:] + nodes[:k]
