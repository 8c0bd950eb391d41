"""The synthetic town's layout: its rolling terrain and its road graph."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Terrain:
    """Gently rolling ground: a few long sine waves, slopes of at most about 2 %."""

    amp: np.ndarray
    k: np.ndarray  # (n,2) wave vectors, rad/m
    phase: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator) -> Terrain:
        n = 3
        wavelength = rng.uniform(150.0, 400.0, n)
        theta = rng.uniform(0, np.pi, n)
        k = (2 * np.pi / wavelength)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
        return cls(rng.uniform(0.15, 0.45, n), k, rng.uniform(0, 2 * np.pi, n))

    def height(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        return sum(a * np.sin(k[0] * x + k[1] * y + p) for a, k, p in zip(self.amp, self.k, self.phase))

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        x, y = np.asarray(x, float), np.asarray(y, float)
        c = [a * np.cos(k[0] * x + k[1] * y + p) for a, k, p in zip(self.amp, self.k, self.phase)]
        return sum(ci * k[0] for ci, k in zip(c, self.k)), sum(ci * k[1] for ci, k in zip(c, self.k))


@dataclass
class RoadGraph:
    """Jittered grid of intersections; edges are straight or bowed roads, some removed."""

    nodes: np.ndarray  # (n,2)
    neighbours: list[list[int]]
    paths: dict[tuple[int, int], np.ndarray]  # (a,b) a<b -> polyline from a to b, ~1 m steps
    half_width: dict[tuple[int, int], float]
    sidewalk: dict[tuple[int, int], float]
    edge_ids: dict[tuple[int, int], int]

    @classmethod
    def random(cls, rng: np.random.Generator, extent: float) -> RoadGraph:
        def axis():
            gaps = rng.uniform(55.0, 85.0, int(2 * extent / 55.0) + 3)
            pos = np.concatenate([[0.0], np.cumsum(gaps)])
            return pos - pos[len(pos) // 2]

        xs, ys = axis(), axis()
        nx, ny = len(xs), len(ys)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        nodes = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-6.0, 6.0, (nx * ny, 2))
        main_x = rng.integers(0, 3)  # every third column / row is a wide main road with parking lanes
        main_y = rng.integers(0, 3)
        edges = []
        for i in range(nx):
            for j in range(ny):
                a = i * ny + j
                if i + 1 < nx:
                    edges.append((a, (i + 1) * ny + j, (j % 3) == main_y))
                if j + 1 < ny:
                    edges.append((a, a + 1, (i % 3) == main_x))
        degree = np.zeros(nx * ny, int)
        for a, b, _ in edges:
            degree[a] += 1
            degree[b] += 1
        kept = []
        for a, b, main in edges:  # drop some side roads, never making a dead end
            if not main and rng.random() < 0.12 and degree[a] > 3 and degree[b] > 3:
                degree[a] -= 1
                degree[b] -= 1
                continue
            kept.append((a, b, main))
        neighbours: list[list[int]] = [[] for _ in range(nx * ny)]
        paths, half_width, sidewalk, ids = {}, {}, {}, {}
        for e, (a, b, main) in enumerate(kept):
            neighbours[a].append(b)
            neighbours[b].append(a)
            pa, pb = nodes[a], nodes[b]
            length = float(np.linalg.norm(pb - pa))
            n = max(int(length), 2)
            t = np.linspace(0, 1, n + 1)[:, None]
            bow = rng.uniform(-12.0, 12.0) if rng.random() < 0.4 else 0.0
            normal = np.array([-(pb - pa)[1], (pb - pa)[0]]) / length
            ctrl = (pa + pb) / 2 + bow * normal
            paths[(a, b)] = (1 - t) ** 2 * pa + 2 * (1 - t) * t * ctrl + t**2 * pb
            half_width[(a, b)] = 5.5 if main else float(rng.choice([4.0, 4.5]))
            sidewalk[(a, b)] = float(rng.uniform(2.5, 4.0))
            ids[(a, b)] = e
        return cls(nodes, neighbours, paths, half_width, sidewalk, ids)

    def path(self, a: int, b: int) -> np.ndarray:
        return self.paths[(a, b)] if a < b else self.paths[(b, a)][::-1]

    def key(self, a: int, b: int) -> tuple[int, int]:
        return (a, b) if a < b else (b, a)


def frames_along(poly: np.ndarray, step: float, offset: float = 0.0):
    """Points every `step` m along a polyline with their arc length and left normal."""
    seg = np.diff(poly, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seglen)])
    s = np.arange(offset, cum[-1], step)
    x = np.interp(s, cum, poly[:, 0])
    y = np.interp(s, cum, poly[:, 1])
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    tangent = seg[idx] / seglen[idx, None]
    return s, np.column_stack([x, y]), np.column_stack([-tangent[:, 1], tangent[:, 0]]), cum[-1]
