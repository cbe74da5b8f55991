"""Gymnasium's own environments (classic control, MuJoCo), by their registered ids."""

from __future__ import annotations

import difflib
from collections.abc import Mapping

import gymnasium as gym

from layered.envs.registry import FAMILIES, EnvFamily, EnvInfo

# Worst and best evaluation return used to normalise the AUC. The best values follow the TLA
# authors' per-environment maxima; Pendulum's worst is their offset of 1550; MountainCar's
# range puts a return of 0 (never reaching the goal) at 0.5, as in the paper's Table 1.
RETURN_RANGES: dict[str, tuple[float, float]] = {
    "Pendulum-v1": (-1550.0, 0.0),
    "MountainCarContinuous-v0": (-100.0, 100.0),
    "InvertedPendulum-v5": (0.0, 1000.0),
    "InvertedDoublePendulum-v5": (0.0, 9400.0),
    "Hopper-v5": (0.0, 3600.0),
    "Walker2d-v5": (0.0, 5000.0),
}


def registered_info(name: str, source: str, return_ranges: Mapping[str, tuple[float, float]]) -> EnvInfo:
    """What is known of `name` in Gymnasium's registry; a KeyError naming the nearest ids where it is not there
    (`source`: whose environments the family offers)."""
    if name not in gym.registry:
        close = difflib.get_close_matches(name, list(gym.registry), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise KeyError(f"no {source} environment {name!r}{hint}")
    return EnvInfo(return_range=return_ranges.get(name), episode_steps=gym.spec(name).max_episode_steps)


@FAMILIES.register("gym")
class GymnasiumFamily(EnvFamily):
    """Any id in Gymnasium's registry (recipes check that its spaces suit layers)."""

    example = "gym:Pendulum-v1"

    def make(self, name: str, render_mode: str | None = None) -> gym.Env:
        self.info(name)
        return gym.make(name, render_mode=render_mode)

    def info(self, name: str) -> EnvInfo:
        return registered_info(name, "Gymnasium", RETURN_RANGES)

    def steps_in_parallel(self, env: gym.Env) -> bool:
        """Gymnasium's MuJoCo tasks (measured on Hopper and HalfCheetah; classic control steps in Python)."""
        return type(env.unwrapped).__module__.startswith("gymnasium.envs.mujoco")
