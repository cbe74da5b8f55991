"""gymnasium-robotics tasks, `robotics:<id>`; goal-conditioned dict observations are flattened.

The flat vector concatenates the dict's entries in Gymnasium's (sorted) key order:
`achieved_goal`, `desired_goal`, `observation`.
"""

from __future__ import annotations

import contextlib
import io
import warnings

import gymnasium as gym
from gymnasium.spaces import Dict
from gymnasium.wrappers import FlattenObservation

from layered.envs.gymnasium_family import registered_info
from layered.envs.registry import FAMILIES, EnvFamily, EnvInfo

# Worst and best return for the AUC: dense maze rewards are exp(-distance) per step and sparse
# ones 1 per step at the goal, over 300 (PointMaze UMaze) or 700 (AntMaze UMaze) steps; Fetch's
# sparse reward is -1 per step away from the goal over 50 steps.
RETURN_RANGES: dict[str, tuple[float, float]] = {
    "PointMaze_UMaze-v3": (0.0, 300.0),
    "PointMaze_UMazeDense-v3": (0.0, 300.0),
    "AntMaze_UMaze-v5": (0.0, 700.0),
    "AntMaze_UMazeDense-v5": (0.0, 700.0),
    "FetchReach-v4": (-50.0, 0.0),
}


def _register() -> None:
    # Importing gymnasium-robotics prints a notice about Adroit reward versions to stderr; keep it quiet.
    with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)


@FAMILIES.register("robotics")
class RoboticsFamily(EnvFamily):
    """Any id that gymnasium-robotics registers (recipes check that its spaces suit layers)."""

    example = "robotics:PointMaze_UMaze-v3"

    def make(self, name: str, render_mode: str | None = None) -> gym.Env:
        self.info(name)
        env = gym.make(name, render_mode=render_mode)
        if isinstance(env.observation_space, Dict):
            env = FlattenObservation(env)
        return env

    def info(self, name: str) -> EnvInfo:
        _register()
        return registered_info(name, "gymnasium-robotics", RETURN_RANGES)

    def timestep(self, env: gym.Env) -> float | None:
        inner = env.unwrapped
        for attribute in ("point_env", "ant_env"):  # the mazes wrap a MuJoCo robot env
            inner = getattr(inner, attribute, inner)
        return getattr(inner, "dt", None)
