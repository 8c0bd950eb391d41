"""The loop route of the synthetic town: laps that come back to the start, a town that does not grow with the drive,
bounded caches for long drives, and the default random drive unchanged."""

import hashlib

import numpy as np
import pytest

from occvo_core.errors import ConfigError
from occvo_core.sim import SyntheticScene
from occvo_core.sim.raster import PEDESTRIAN


@pytest.fixture(scope="module")
def loop():
    return SyntheticScene(seed=1, frames=200, route="loop", loop_blocks=(1, 1))


def test_loop_comes_back_to_its_start_every_lap(loop):
    assert len(loop.lap_starts) >= 3  # two full laps in 100 s round one block
    poses = loop.gt_poses
    start, yaw0 = poses[0, :2, 3], np.arctan2(poses[0, 1, 0], poses[0, 0, 0])
    step = loop.speeds.max() / loop.rate_hz
    for k in loop.lap_starts[1:]:
        near = [np.linalg.norm(poses[j, :2, 3] - start) for j in (k - 1, k)]
        assert min(near) <= step / 2 + 0.5, (k, near)  # the start lies between the frames around the lap boundary
        yaw = np.arctan2(poses[k, 1, 0], poses[k, 0, 0])
        assert abs(np.angle(np.exp(1j * (yaw - yaw0)))) < np.radians(15)
    # in between, the ego goes round the block, not back and forth
    far = np.linalg.norm(poses[: loop.lap_starts[1], :2, 3] - start, axis=1).max()
    assert 40.0 < far < loop.lap_length_m / 2
    assert 150.0 < loop.lap_length_m < 400.0


def test_loop_traffic_keeps_clear_of_the_ego(loop):
    vehicles = [t for t in loop.dynamic_tracks() if t.label != PEDESTRIAN]
    assert len(vehicles) >= 3 and any(t.label == PEDESTRIAN for t in loop.dynamic_tracks())
    ego = loop.gt_poses[:, :2, 3]
    for t in vehicles:
        gap = np.linalg.norm(t.poses[:, :2, 3] - ego, axis=1).min()
        assert gap > 2.5, (t.id, gap)  # oncoming traffic passes a lane apart (3.5 m), followers keep 20 m of road
    ids = [t.id for t in loop.dynamic_tracks()]
    assert ids == list(range(len(ids)))


def test_long_drive_caches_little_and_town_stays_the_loops(loop):
    s = SyntheticScene(seed=1, frames=600, route="loop", loop_blocks=(1, 1), traffic=False)
    assert s.cache_frames == 8 and not s.keep_static
    first = s[0]
    for i in range(1, 20):
        s[i]
    assert len(s._frames) <= 8 and 0 not in s._frames and not s._static
    again = s[0]  # rendered anew, bit for bit
    assert np.array_equal(again.points, first.points) and np.array_equal(again.labels, first.labels)
    assert s.town.shape == loop.town.shape  # the town covers the circuit, whatever the drive's length
    assert len(s.lap_starts) > len(loop.lap_starts)


def test_static_map_without_bookkeeping_is_the_same():
    kept = SyntheticScene(seed=7, frames=4, traffic=False)
    streamed = SyntheticScene(seed=7, frames=4, traffic=False, keep_static=False)
    for a, b in zip(kept.static_map(), streamed.static_map()):
        assert np.array_equal(a, b)
    assert not streamed._static
    part = kept.static_map(frames=[1, 2])
    assert 0 < len(part[0]) < len(kept.static_map()[0])


def test_default_drive_is_unchanged():
    # digest of the default route's poses, frames, static map and tracks: the loop route leaves that drive unchanged
    s = SyntheticScene(seed=7, frames=6)
    assert s.route == "walk" and s.cache_frames is None and s.keep_static
    h = hashlib.sha256(s.gt_poses.tobytes())
    for i in range(6):
        f = s[i]
        h.update(f.points.tobytes())
        h.update(f.labels.tobytes())
    p, lab = s.static_map()
    h.update(p.tobytes())
    h.update(lab.tobytes())
    for tr in s.tracks:
        h.update(tr.poses.tobytes())
    assert h.hexdigest() == "6204d9210474a3374e4716a1999360aebb1f0a2a9699912fdf6ec7f4e4e14a70"


def test_bad_route_arguments_are_config_errors():
    with pytest.raises(ConfigError):
        SyntheticScene(route="figure8")
    with pytest.raises(ConfigError):
        SyntheticScene(cache_frames=-1)
    with pytest.raises(ConfigError):
        SyntheticScene(route="loop", loop_blocks=(0, 2))
