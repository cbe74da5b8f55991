"""K environments of one id, one per seed, stepped and reset together by masks over the rows.

Each row is an environment of its own, made and seeded exactly as a single run makes and seeds its
environment, so a row's episodes are the ones that seed would see alone. The rows are stepped one
after the other in this process.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.spaces import Box

from layered.envs import make_env, restore_env, snapshot_env


class EnvGroup:
    """K environments with their latest observations as one `[K, obs]` array."""

    def __init__(self, env_id: str, rows: int) -> None:
        self.env_id = env_id
        self.envs = [make_env(env_id) for _ in range(rows)]
        space = self.envs[0].observation_space
        action_space = self.envs[0].action_space
        assert isinstance(space, Box) and isinstance(action_space, Box), "the recipe checks refuse other spaces"
        self.observation_space, self.action_space = space, action_space
        self.obs = np.zeros((rows, *(space.shape or ())), np.float32)

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        """Start an episode in each row of the `rows` mask; `seeds[k]` seeds row k's environment (None:
        its generator goes on)."""
        for k in np.flatnonzero(rows).tolist():
            self.obs[k], _ = self.envs[k].reset(seed=seeds[k])
            if seeds[k] is not None:
                self.envs[k].action_space.seed(seeds[k])

    def step(self, actions: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Execute `actions[k]` in each row of the `rows` mask: the rewards, terminations and
        truncations ([K]; zero and False in the other rows), the observations updated in `obs`."""
        reward = np.zeros(len(self.envs))
        terminated = np.zeros(len(self.envs), bool)
        truncated = np.zeros(len(self.envs), bool)
        for k in np.flatnonzero(rows).tolist():
            self.obs[k], r, terminated[k], truncated[k], _ = self.envs[k].step(actions[k])
            reward[k] = float(r)
        return reward, terminated, truncated

    def snapshots(self) -> list[dict[str, Any]]:
        """Each row's simulator state, mid-episode or not, as `restore` takes it (for a group's checkpoint)."""
        return [snapshot_env(self.env_id, env) for env in self.envs]

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        """Put every row where `snapshots` found it, `obs` its latest observations."""
        for env, snapshot in zip(self.envs, snapshots, strict=True):
            restore_env(self.env_id, env, snapshot)
        self.obs[:] = obs

    def close(self) -> None:
        for env in self.envs:
            env.close()
