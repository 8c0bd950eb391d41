"""Gymnasium environments: registration, check_env, episode semantics, reward, the OccVO agent."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import occvo_core.envs  # noqa: F401  (registers the environments)
from occvo_core.envs import ReplayEnv, action_from_pose, frame_from_observation, pose_from_action, run_occvo_agent
from occvo_core.sim import SyntheticScene

SAMPLE = Path(__file__).resolve().parents[3] / "shared/data/occvo-sample"


def test_registered_ids():
    assert "occvo/Replay-v0" in gym.registry and "occvo/Synthetic-v0" in gym.registry


def test_check_env_synthetic():
    env = gym.make("occvo/Synthetic-v0", frames=3)
    check_env(env.unwrapped, skip_render_check=True)


def test_check_env_replay_over_a_source():
    check_env(ReplayEnv(SyntheticScene(seed=1, frames=3)), skip_render_check=True)


def test_episode_reward_and_info():
    scene = SyntheticScene(seed=2, frames=4)
    env = ReplayEnv(scene)
    obs, info = env.reset()
    assert info["frame_index"] == 0 and np.allclose(info["gt_pose"], scene.gt_poses[0])
    frame = frame_from_observation(obs)
    assert np.array_equal(frame.points, scene[0].points) and np.array_equal(frame.labels, scene[0].labels)
    # perfect estimates in a different world frame: zero error after aligning first poses
    offset = np.eye(4)
    offset[:3, 3] = [100.0, -50.0, 3.0]
    gt = scene.gt_poses
    est = np.linalg.inv(gt[0]) @ gt  # first pose identity, as OccVO reports
    rewards = []
    for i in range(4):
        obs, reward, terminated, truncated, info = env.step(action_from_pose(offset @ est[i]))
        rewards.append(reward)
        assert info["scored_index"] == i and terminated == (i == 3) and not truncated
    assert np.allclose(rewards, 0.0, atol=1e-6)
    with pytest.raises(RuntimeError):
        env.step(action_from_pose(np.eye(4)))
    # an estimate 1 m off in the second frame costs 1
    env.reset()
    env.step(action_from_pose(est[0]))
    wrong = est[1].copy()
    wrong[:3, 3] += [0.0, 1.0, 0.0]
    _, reward, *_ = env.step(action_from_pose(wrong))
    assert reward == pytest.approx(-1.0)


def test_pose_action_round_trip():
    pose = np.eye(4)
    pose[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    pose[:3, 3] = [1, 2, 3]
    assert np.allclose(pose_from_action(action_from_pose(pose)), pose)
    assert np.allclose(pose_from_action(np.zeros(7))[:3, :3], np.eye(3))  # zero quaternion: identity


def test_seed_selects_the_town():
    env = gym.make("occvo/Synthetic-v0", frames=2)
    a, _ = env.reset(seed=3)
    b, _ = env.reset(seed=4)
    c, info = env.reset(seed=3)
    assert info["scene"] == "synthetic-0003"
    assert a["count"] == c["count"] and np.array_equal(a["points"], c["points"])
    assert not (a["count"] == b["count"] and np.array_equal(a["points"], b["points"]))


def test_occvo_agent_tracks_a_synthetic_scene():
    result = run_occvo_agent(gym.make("occvo/Synthetic-v0", frames=8), seed=1)
    assert result["frames"] == 8 and result["rejected_frames"] == 0
    assert result["mean_translation_error"] < 0.5


@pytest.mark.skipif(not (SAMPLE / "occupancy/scene-0101").is_dir(), reason="needs ../shared/data/occvo-sample")
def test_replay_over_the_release_sample():
    env = gym.make("occvo/Replay-v0", source=str(SAMPLE / "occupancy/scene-0101"))
    obs, info = env.reset()
    assert obs["count"] > 1000 and info["gt_pose"] is not None


def test_single_frame_episode_passes_check_env():
    check_env(gym.make("occvo/Synthetic-v0", frames=1).unwrapped, skip_render_check=True)


def test_max_episode_steps_is_the_scenes_length_and_never_cuts_an_episode():
    env = gym.make("occvo/Synthetic-v0", frames=5)
    assert env.spec.max_episode_steps == 5
    env.reset(seed=0)
    flags = [env.step(action_from_pose(np.eye(4)))[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(True, False)]
    replay = gym.make("occvo/Replay-v0", source=SyntheticScene(seed=1, frames=3))
    assert replay.spec.max_episode_steps == 3


def test_check_env_with_render():
    env = gym.make("occvo/Synthetic-v0", frames=3, render_mode="rgb_array")
    check_env(env.unwrapped)


def test_rgb_array_shows_the_map_where_the_estimates_put_it_and_the_path():
    """Perfect estimates: the image holds the frames' class colours and the orange path; an estimate 30 m off puts
    the last frame's voxels and its path point elsewhere, so the image changes."""
    from occvo_core.envs.birds_eye import EST_COLOUR

    scene = SyntheticScene(seed=2, frames=4)
    images = []
    for shift in (0.0, 30.0):
        env = ReplayEnv(scene, render_mode="rgb_array")
        env.reset()
        assert (env.render() == 255).all()  # nothing scored yet: a blank page
        for i in range(4):
            pose = np.linalg.inv(scene.gt_poses[0]) @ scene.gt_poses[i]
            pose[:3, 3] += [shift * (i == 3), 0.0, 0.0]
            env.step(action_from_pose(pose))
        img = env.render()
        assert img.shape == (512, 512, 3) and img.dtype == np.uint8
        assert (img == EST_COLOUR).all(axis=2).sum() >= 9 and (img != 255).any(axis=2).mean() > 0.05
        images.append(img)
    assert not np.array_equal(*images)
    assert ReplayEnv(scene).render() is None
    with pytest.raises(ValueError, match="render_mode"):
        ReplayEnv(scene, render_mode="human")
