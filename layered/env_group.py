"""K environments of one id, one per seed, stepped and reset together by masks over the rows.

Each row is an environment of its own, made and seeded exactly as a single run makes and seeds its
environment, so a row's episodes are the ones that seed would see alone. `EnvGroup` steps its rows one
after the other in this process; `layered.env_workers` steps the same rows in worker processes, each
row by the same functions (`step_rows`, `reset_rows`), so where the rows are stepped changes no number.

A step is asked for (`step_async`) and then collected (`step_wait`), so that a caller can queue work in
between (a group queues its update): in worker processes the rows step meanwhile; here they step when
collected, after the queued work is launched.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box

from layered.envs import make_env, restore_env, snapshot_env

StepResult = tuple[np.ndarray, np.ndarray, np.ndarray]
"""The rewards, terminations and truncations of one step of every row ([K] each; zero and False in the
rows not stepped)."""


class Envs(Protocol):
    """K environments of one id with their latest observations as one `[K, obs]` array, in this process or not."""

    env_id: str
    observation_space: Box
    action_space: Box
    obs: np.ndarray

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        """Start an episode in each row of the `rows` mask; `seeds[k]` seeds row k's environment (None:
        its generator goes on)."""

    def step_async(self, actions: np.ndarray, rows: np.ndarray) -> None:
        """Ask for `actions[k]` ([K, action]) to be executed in each row of the `rows` mask."""

    def step_wait(self) -> StepResult:
        """The asked-for step's results, the observations updated in `obs`."""

    def step(self, actions: np.ndarray, rows: np.ndarray) -> StepResult:
        """`step_async` and `step_wait` at once."""
        self.step_async(actions, rows)
        return self.step_wait()

    def snapshots(self) -> list[dict[str, Any]]:
        """Each row's simulator state, mid-episode or not, as `restore` takes it (for a group's checkpoint)."""

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        """Put every row where `snapshots` found it, `obs` its latest observations."""

    def close(self) -> None:
        """Close every environment (and stop any worker)."""


def step_rows(envs: Sequence[gym.Env], actions: np.ndarray, rows: np.ndarray, obs: np.ndarray,
              result: StepResult) -> None:
    """Step `envs[k]` with `actions[k]` for each k in the `rows` mask, writing its observation into `obs[k]`
    and its reward and flags into `result`'s row k (the other rows are left as they are)."""
    reward, terminated, truncated = result
    for k in np.flatnonzero(rows).tolist():
        obs[k], r, terminated[k], truncated[k], _ = envs[k].step(actions[k].astype(np.float32))
        reward[k] = float(r)


def reset_rows(envs: Sequence[gym.Env], rows: np.ndarray, seeds: Sequence[int | None], obs: np.ndarray) -> None:
    """Reset `envs[k]` for each k in the `rows` mask, seeded with `seeds[k]` (its action space too) unless None."""
    for k in np.flatnonzero(rows).tolist():
        obs[k], _ = envs[k].reset(seed=seeds[k])
        if seeds[k] is not None:
            envs[k].action_space.seed(seeds[k])


def spaces(env: gym.Env) -> tuple[Box, Box]:
    """An environment's observation and action spaces, both boxes (the recipe checks refuse other spaces)."""
    space, action_space = env.observation_space, env.action_space
    assert isinstance(space, Box) and isinstance(action_space, Box), "the recipe checks refuse other spaces"
    return space, action_space


class EnvGroup(Envs):
    """K environments stepped one after the other in this process (`Envs`)."""

    def __init__(self, env_id: str, rows: int) -> None:
        self.env_id = env_id
        self.envs = [make_env(env_id) for _ in range(rows)]
        self.observation_space, self.action_space = spaces(self.envs[0])
        self.obs = np.zeros((rows, *(self.observation_space.shape or ())), np.float32)
        self._asked: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        reset_rows(self.envs, rows, seeds, self.obs)

    def step_async(self, actions: np.ndarray, rows: np.ndarray) -> None:
        self._asked = (actions, rows)

    def step_wait(self) -> StepResult:
        assert self._asked is not None, "step_wait collects the step step_async asked for"
        (actions, rows), self._asked = self._asked, None
        result = (np.zeros(len(self.envs)), np.zeros(len(self.envs), bool), np.zeros(len(self.envs), bool))
        step_rows(self.envs, actions, rows, self.obs, result)
        return result

    def snapshots(self) -> list[dict[str, Any]]:
        return [snapshot_env(self.env_id, env) for env in self.envs]

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        for env, snapshot in zip(self.envs, snapshots, strict=True):
            restore_env(self.env_id, env, snapshot)
        self.obs[:] = obs

    def close(self) -> None:
        for env in self.envs:
            env.close()
