"""Gymnasium environments over occupancy scenes (see occvo_core.envs.replay for spaces, reward and info).

import gymnasium as gym, occvo_core.envs
env = gym.make("occvo/Synthetic-v0", frames=40, noise="default")      # reset(seed=s): town s
env = gym.make("occvo/Replay-v0", source="path/to/occupancy/scene-0101")
result = run_occvo_agent(env)                                          # OccVO as the agent
"""

from __future__ import annotations

from collections import OrderedDict

import gymnasium as gym
from gymnasium.wrappers import TimeLimit

from occvo_core.envs.replay import (
    ReplayEnv,
    action_from_pose,
    frame_from_observation,
    pose_from_action,
    run_occvo_agent,
)

ENV_IDS = ("occvo/Replay-v0", "occvo/Synthetic-v0")


class SyntheticEnv(ReplayEnv):
    """ReplayEnv over SyntheticScene(seed, ...): reset(seed=s) (or options={"scene_seed": s}) replays town s."""

    def __init__(
        self,
        seed: int = 0,
        frames: int = 40,
        rate_hz: float = 2.0,
        noise="default",
        traffic: bool = True,
        capacity: int | None = None,
        cache: int = 2,
        render_mode: str | None = None,
    ):
        from occvo_core.sim import SyntheticScene

        self._scenes: OrderedDict[int, SyntheticScene] = OrderedDict()

        def scene_for_seed(s: int) -> SyntheticScene:
            if s not in self._scenes:
                self._scenes[s] = SyntheticScene(seed=s, frames=frames, rate_hz=rate_hz, noise=noise, traffic=traffic)
                while len(self._scenes) > cache:
                    self._scenes.popitem(last=False)
            return self._scenes[s]

        kwargs = {} if capacity is None else {"capacity": capacity}
        super().__init__(scene_for_seed(seed), scene_for_seed=scene_for_seed, render_mode=render_mode, **kwargs)


class SceneLength(TimeLimit):
    """TimeLimit at the scene's length, so env.spec.max_episode_steps is known; it never cuts an episode short (the
    last step terminates it, and is not also reported truncated)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated and not terminated, info


def make_replay(**kwargs) -> gym.Env:
    env = ReplayEnv(**kwargs)
    return SceneLength(env, max_episode_steps=len(env.source))


def make_synthetic(**kwargs) -> gym.Env:
    env = SyntheticEnv(**kwargs)
    return SceneLength(env, max_episode_steps=len(env.source))


def register_envs() -> None:
    """Register occvo/Replay-v0 and occvo/Synthetic-v0 (idempotent)."""
    if "occvo/Replay-v0" not in gym.registry:
        gym.register(id="occvo/Replay-v0", entry_point="occvo_core.envs:make_replay")
    if "occvo/Synthetic-v0" not in gym.registry:
        gym.register(id="occvo/Synthetic-v0", entry_point="occvo_core.envs:make_synthetic")


register_envs()

__all__ = [
    "ReplayEnv",
    "SyntheticEnv",
    "register_envs",
    "run_occvo_agent",
    "ENV_IDS",
    "frame_from_observation",
    "pose_from_action",
    "action_from_pose",
]
