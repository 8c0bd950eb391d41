"""Moving traffic: vehicles driving their own lane paths through the road graph, pedestrians on sidewalks and crossings."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.sim.raster import BICYCLE, BUS, CAR, MOTORCYCLE, PEDESTRIAN, TRUCK, VEHICLE_SIZE, Town
from occvo_core.sim.route import lane_path, random_walk, resample, speed_profile


@dataclass
class DynamicTrack:
    """One moving object: class, box size, and its world pose at every frame (bottom centre on the ground, yaw only)."""

    id: int
    label: int
    size: tuple[float, float, float]  # length, width, height (m)
    clearance: float  # box bottom above the ground (m)
    poses: np.ndarray  # (T,4,4) world
    speeds: np.ndarray  # (T,) m/s

    def box_centre_height(self) -> float:
        return (self.clearance + self.size[2]) / 2


def _pose(town: Town, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    out = np.tile(np.eye(4), (len(xy), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, :2, 3] = xy
    out[:, 2, 3] = town.ground_height(xy[:, 0], xy[:, 1])
    return out


def make_traffic(
    town: Town,
    rng: np.random.Generator,
    times: np.ndarray,
    ego_xy: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    n_vehicles: int,
    n_pedestrians: int,
    avoid: list | None = None,
    first_id: int = 0,
) -> list[DynamicTrack]:
    """Agents whose paths never come near the ego or each other (no collisions to explain).
    avoid: (positions at 0.25 s steps, radius) of agents placed already, kept clear of too."""
    graph = town.graph
    duration = float(times[-1]) if len(times) else 0.0
    check_t = np.arange(0.0, duration + 1e-9, 0.25)
    ego_at = np.column_stack([np.interp(check_t, times, ego_xy[:, 0]), np.interp(check_t, times, ego_xy[:, 1])])
    near = np.nonzero(np.all((graph.nodes > lower + 20) & (graph.nodes < upper - 20), axis=1))[0]
    tracks: list[DynamicTrack] = []
    placed: list[tuple[np.ndarray, float]] = list(avoid or [])  # (positions at check_t, radius)

    def clear(pos: np.ndarray, radius: float) -> bool:
        if np.min(np.linalg.norm(pos - ego_at, axis=1)) < radius + 4.0:
            return False
        return all(np.min(np.linalg.norm(pos - p, axis=1)) > radius + r + 0.8 for p, r in placed)

    attempts = 0
    while sum(t.label != PEDESTRIAN for t in tracks) < n_vehicles and attempts < 20 * max(n_vehicles, 1) and len(near):
        attempts += 1
        r = rng.random()
        label = CAR if r < 0.7 else TRUCK if r < 0.8 else BUS if r < 0.87 else MOTORCYCLE if r < 0.94 else BICYCLE
        cruise = rng.uniform(4.0, 6.0) if label == BICYCLE else rng.uniform(6.0, 11.0)
        start = int(near[rng.integers(len(near))])
        prev = graph.neighbours[start][rng.integers(len(graph.neighbours[start]))]
        nodes = random_walk(graph, rng, start, prev, cruise * duration + 80.0)
        path = lane_path(graph, nodes)
        motion = speed_profile(path, np.full(len(path.xy), cruise), cruise)
        t0 = rng.uniform(0.0, 3.0)
        xy, yaw = motion.xy_heading(times + t0)
        pos = np.column_stack([np.interp(check_t, times, xy[:, 0]), np.interp(check_t, times, xy[:, 1])])
        length, width, height, clearance = VEHICLE_SIZE[label]
        if not clear(pos, length / 2):
            continue
        placed.append((pos, length / 2))
        tracks.append(
            DynamicTrack(
                first_id + len(tracks),
                label,
                (length, width, height),
                clearance,
                _pose(town, xy, yaw),
                motion.speed_at(times + t0),
            )
        )

    attempts = 0
    while (
        sum(t.label == PEDESTRIAN for t in tracks) < n_pedestrians
        and attempts < 20 * max(n_pedestrians, 1)
        and len(near)
    ):
        attempts += 1
        a = int(near[rng.integers(len(near))])
        b = graph.neighbours[a][rng.integers(len(graph.neighbours[a]))]
        key = graph.key(a, b)
        centre = resample(graph.path(a, b), 0.5)
        tangent = np.gradient(centre, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
        side = rng.choice([-1.0, 1.0])
        off = graph.half_width[key] + graph.sidewalk[key] * rng.uniform(0.3, 0.7)
        walk = centre + side * off * normal
        if rng.random() < 0.3:  # crosses the road at a random point, then walks on along the far side
            k = int(rng.integers(len(walk) // 4, 3 * len(walk) // 4))
            walk = np.concatenate([walk[: k + 1], centre[k:] - side * off * normal[k:]])
        speed = rng.uniform(0.9, 1.6)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(walk, axis=0), axis=1))])
        direction = rng.choice([-1.0, 1.0])
        s0 = rng.uniform(0.2, 0.8) * cum[-1]
        s = s0 + direction * speed * times
        period = 2 * cum[-1]
        s = np.abs(((s % period) + period) % period)
        s = np.where(s > cum[-1], period - s, s)  # walks back at the path's end
        xy = np.column_stack([np.interp(s, cum, walk[:, 0]), np.interp(s, cum, walk[:, 1])])
        ds = np.gradient(s) if len(s) > 1 else np.ones(1)
        step = np.gradient(xy, axis=0) if len(xy) > 1 else np.array([[1.0, 0.0]])
        yaw = np.arctan2(step[:, 1], step[:, 0])
        pos = np.column_stack([np.interp(check_t, times, xy[:, 0]), np.interp(check_t, times, xy[:, 1])])
        if not clear(pos, 0.4):
            continue
        placed.append((pos, 0.4))
        length, width, height, clearance = VEHICLE_SIZE[PEDESTRIAN]
        tracks.append(
            DynamicTrack(
                first_id + len(tracks),
                PEDESTRIAN,
                (length, width, rng.uniform(1.55, 1.9)),
                clearance,
                _pose(town, xy, yaw),
                np.full(len(times), speed) * (np.abs(ds) > 0),
            )
        )
    return tracks


def loop_traffic(
    town: Town,
    rng: np.random.Generator,
    times: np.ndarray,
    ego,
    cycle: list[int],
    lap_m: float,
    n_ahead: int,
    n_oncoming: int,
) -> tuple[list[DynamicTrack], list]:
    """Traffic on a closed circuit: vehicles in the ego's lane driving its own speed profile some seconds ahead
    (time-shifted copies of `ego`, a route.Motion, so they stop where it stops), and oncoming vehicles in the
    other lane going round the opposite way. Lane followers keep >= 20 m of arc from the ego and each other;
    oncoming ones keep that among themselves and pass the ego a lane apart. Also returns their (positions at
    0.25 s steps, radius) for make_traffic's `avoid`."""
    duration = float(times[-1]) if len(times) else 0.0
    check_t = np.arange(0.0, duration + 1e-9, 0.25)
    ego_s = np.mod(ego.s_at(check_t), lap_m)
    s_end = float(ego.s_knots[-1])
    tracks: list[DynamicTrack] = []
    placed: list[tuple[np.ndarray, float]] = []

    def pick_label():
        r = rng.random()
        return CAR if r < 0.75 else TRUCK if r < 0.85 else BUS if r < 0.92 else MOTORCYCLE

    def gap_ok(s, others):
        return all(np.min(np.abs((s - o + lap_m / 2) % lap_m - lap_m / 2)) >= 20.0 for o in others)

    def add_vehicle(motion, shift: float) -> None:
        """A vehicle of a random class driving `motion` `shift` seconds ahead of the clock."""
        label = pick_label()
        xy, yaw = motion.xy_heading(times + shift)
        length, width, height, clearance = VEHICLE_SIZE[label]
        placed.append(
            (np.column_stack([np.interp(check_t, times, xy[:, 0]), np.interp(check_t, times, xy[:, 1])]), length / 2)
        )
        tracks.append(
            DynamicTrack(
                len(tracks),
                label,
                (length, width, height),
                clearance,
                _pose(town, xy, yaw),
                motion.speed_at(times + shift),
            )
        )

    lap_s = float(np.interp(lap_m, ego.s_knots, ego.t_knots))  # time of the first lap
    taken = [ego_s]
    for _ in range(20 * max(n_ahead, 1)):
        if len(tracks) >= n_ahead or lap_s < 40.0:
            break
        shift = rng.uniform(10.0, lap_s - 10.0)
        if ego.s_at(duration + shift) >= s_end - 1.0:
            continue
        s = np.mod(ego.s_at(check_t + shift), lap_m)
        if not gap_ok(s, taken):
            continue
        taken.append(s)
        add_vehicle(ego, shift)

    if n_oncoming > 0:
        back = cycle[::-1]
        cruise = rng.uniform(7.0, 11.0)
        laps = int(np.ceil((cruise * duration + 2 * lap_m + 100.0) / lap_m)) + 1
        path = lane_path(town.graph, back * laps + back[:1])
        lap_r = float(path.node_s[len(back)] - path.node_s[0])  # the other lane's lap is a little different
        motion = speed_profile(path, np.full(len(path.xy), cruise), cruise)
        lap_back = float(np.interp(lap_r, motion.s_knots, motion.t_knots))
        taken_r: list[np.ndarray] = []
        for _ in range(20 * n_oncoming):
            if len(taken_r) >= n_oncoming:
                break
            t0 = rng.uniform(0.0, lap_back)
            s = np.mod(motion.s_at(check_t + t0), lap_r)
            if not all(np.min(np.abs((s - o + lap_r / 2) % lap_r - lap_r / 2)) >= 20.0 for o in taken_r):
                continue
            taken_r.append(s)
            add_vehicle(motion, t0)
    return tracks, placed


def boxes_in_ego(tracks: list[DynamicTrack], frame: int, ego_pose: np.ndarray) -> np.ndarray:
    """(n,16) rows for render_boxes: rotation box->ego (9), centre (3), half extents (3), label."""
    inv = np.linalg.inv(ego_pose)
    rows = []
    for tr in tracks:
        world = tr.poses[frame].copy()
        world[:3, 3] = world[:3, 3] + world[:3, 2] * tr.box_centre_height()
        rel = inv @ world
        if np.abs(rel[:2, 3]).max() > 48.0:
            continue
        length, width, height = tr.size
        half = (length / 2, max(width / 2, 0.3), (height - tr.clearance) / 2)
        rows.append(np.concatenate([rel[:3, :3].ravel(), rel[:3, 3], half, [tr.label]]))
    return np.array(rows, np.float64).reshape(-1, 16)
