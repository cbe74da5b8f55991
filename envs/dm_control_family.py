"""dm_control suite tasks as Gymnasium envs: `dmc:<domain>-<task>`, e.g. `dmc:cartpole-swingup`.

The adapter flattens the observation dict (in the spec's key order) into one float32 vector,
exposes the action spec as a Box, seeds the task's random state on `reset(seed=...)`, and turns
the end of an episode into `terminated` (discount 0) or `truncated` (the time limit).
"""

from __future__ import annotations

import difflib
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box

from layered.envs.registry import FAMILIES, EnvFamily, EnvInfo

if TYPE_CHECKING:
    from layered.envs.state import StateRules

# Every suite task pays a reward in [0, 1] per control step over 1000 steps, but those of the domains that end
# only where the task says (the linear-quadratic regulators run until their state settles: no time limit).
SUITE_RETURN_RANGE = (0.0, 1000.0)
SUITE_EPISODE_STEPS = 1000
UNLIMITED_DOMAINS = frozenset({"lqr"})


def _flatten(observation: dict[str, Any]) -> np.ndarray:
    return np.concatenate([np.asarray(v, np.float64).ravel() for v in observation.values()]).astype(np.float32)


class DmControlEnv(gym.Env[np.ndarray, np.ndarray]):
    """One dm_control suite task behind the Gymnasium API."""

    def __init__(self, domain: str, task: str, render_mode: str | None = None,
                 width: int = 320, height: int = 240, camera_id: int = 0) -> None:
        from dm_control import suite

        self._env = suite.load(domain, task)
        self.render_mode = render_mode
        self._render_size, self._camera = (height, width), camera_id
        size = sum(int(np.prod(spec.shape)) for spec in self._env.observation_spec().values())
        self.observation_space = Box(-np.inf, np.inf, (size,), np.float32)
        spec = self._env.action_spec()
        self.action_space = Box(spec.minimum.astype(np.float32), spec.maximum.astype(np.float32), dtype=np.float32)
        self.dt = float(self._env.control_timestep())
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / self.dt)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        # The task draws its initial state from its own RandomState; derive it from Gymnasium's.
        self._env.task._random = np.random.RandomState(int(self.np_random.integers(2**31)))
        return _flatten(self._env.reset().observation), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        ts = self._env.step(np.asarray(action, np.float64))
        terminated = bool(ts.last() and ts.discount == 0.0)
        truncated = bool(ts.last() and not terminated)
        return _flatten(ts.observation), float(ts.reward or 0.0), terminated, truncated, {}

    def render(self) -> np.ndarray:
        height, width = self._render_size
        return self._env.physics.render(height=height, width=width, camera_id=self._camera)

    def close(self) -> None:
        self._env.close()


@FAMILIES.register("dmc")
class DmControlFamily(EnvFamily):
    """The dm_control suite's (domain, task) pairs, named `domain-task`."""

    example = "dmc:cartpole-balance"

    def _split(self, name: str) -> tuple[str, str]:
        from dm_control import suite

        domain, _, task = name.partition("-")
        if (domain, task) not in suite.ALL_TASKS:
            known = [f"{d}-{t}" for d, t in suite.ALL_TASKS]
            close = difflib.get_close_matches(name, known, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else "; names are domain-task, e.g. cartpole-swingup"
            raise KeyError(f"no dm_control suite task {name!r}{hint}")
        return domain, task

    def make(self, name: str, render_mode: str | None = None) -> gym.Env:
        return DmControlEnv(*self._split(name), render_mode=render_mode)

    def info(self, name: str) -> EnvInfo:
        domain, _ = self._split(name)
        if domain in UNLIMITED_DOMAINS:
            return EnvInfo(return_range=None, episode_steps=None)
        return EnvInfo(return_range=SUITE_RETURN_RANGE, episode_steps=SUITE_EPISODE_STEPS)

    def state_rules(self) -> StateRules:
        """The common rules and dm_control's physics, which wraps its MuJoCo model and data."""
        from dm_control.mujoco.engine import Physics

        from layered.envs.mujoco_state import load_physics, save_physics
        from layered.envs.state import Capture, StateRules

        physics = Capture("dm_control_physics", (Physics,), save_physics, load_physics)
        return super().state_rules() + StateRules(captures=(physics,), static=())
