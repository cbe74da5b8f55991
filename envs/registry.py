"""The registry of environment families, the per-environment constants the metrics need, and snapshots of
environments that a checkpoint taken mid-episode continues exactly."""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box, Space

from layered.envs.rendering import RenderingUnavailable, check_can_render
from layered.registry import Registry

if TYPE_CHECKING:
    from layered.envs.state import StateRules

DEFAULT_FAMILY = "gym"


@dataclass(frozen=True)
class EnvInfo:
    """Constants of one environment: `return_range` (worst, best) normalises returns for the AUC;
    `episode_steps` is the time limit of an episode in base steps."""

    return_range: tuple[float, float] | None
    episode_steps: int | None = None


class EnvFamily(ABC):
    """A source of environments sharing one naming scheme."""

    example: ClassVar[str]
    """One id of the family (with its `family:` prefix): the registry's tests train and resume on it."""

    @abstractmethod
    def make(self, name: str, render_mode: str | None = None) -> gym.Env:
        """A new Gymnasium env for `name`, its time limit reported as truncation."""

    @abstractmethod
    def info(self, name: str) -> EnvInfo:
        """Constants of `name`; raises KeyError naming the problem when `name` is unknown."""

    def timestep(self, env: gym.Env) -> float | None:
        """Seconds of one base step of `env`, or None when the environment does not define it."""
        dt = getattr(env.unwrapped, "dt", None)
        return None if dt is None else float(dt)

    def steps_in_parallel(self, env: gym.Env) -> bool:
        """Whether rows of `env` step faster in threads of one process: its step runs mostly outside Python's
        lock, as a costly MuJoCo simulation's does. No unless measured: rows whose step is mostly Python only
        take turns, more slowly than one after another (dm_control's cartpole and gymnasium-robotics' point maze
        did, dm_control's walker did not: docs/performance.md)."""
        return False

    def state_rules(self) -> StateRules:
        """What a snapshot captures beyond plain data (envs/state.py): random generators, MuJoCo models and
        data (imported here, so that importing the envs loads neither torch nor MuJoCo)."""
        from layered.envs.mujoco_state import MUJOCO
        from layered.envs.state import GENERATORS, INTERFACE

        return GENERATORS + MUJOCO + INTERFACE

    def snapshot(self, env_id: str, env: gym.Env) -> dict[str, Any]:
        """Everything needed to continue `env` (made by `make_env(env_id)`) exactly, mid-episode or not."""
        from layered.envs.state import StateError, StateWalk

        try:
            return StateWalk(self.state_rules(), functools.partial(_fresh_env, env_id)).save(env)
        except StateError as error:
            raise ValueError(f"{env_id} cannot be checkpointed mid-episode: {error}") from None

    def restore(self, env_id: str, env: gym.Env, state: dict[str, Any]) -> None:
        """Put `env` (made by `make_env(env_id)`, used or not) into the state `snapshot` saved."""
        from layered.envs.state import StateError, StateWalk

        try:
            StateWalk(self.state_rules(), functools.partial(_fresh_env, env_id)).restore(env, state)
        except StateError as error:
            raise ValueError(f"cannot restore a snapshot into {env_id}: {error}") from None


FAMILIES: Registry[type[EnvFamily]] = Registry("environment family", EnvFamily)


def split_id(env_id: str) -> tuple[str, str]:
    """(family, name) of an id such as `dmc:cartpole-swingup`; a bare id is a Gymnasium id."""
    family, sep, name = env_id.partition(":")
    return (family, name) if sep else (DEFAULT_FAMILY, env_id)


def make_env(env_id: str, render_mode: str | None = None) -> gym.Env:
    """A new environment for a recipe id; asked to render where MuJoCo has no GL backend, RenderingUnavailable."""
    family, name = split_id(env_id)
    env = FAMILIES.get(family)().make(name, render_mode=render_mode)
    if render_mode is not None:
        try:
            check_can_render(type(env.unwrapped).__module__)
        except RenderingUnavailable:
            env.close()
            raise
    return env


@functools.cache
def _fresh_env(env_id: str) -> gym.Env:
    """An env of `env_id` as made, never reset: what snapshots save the changes of MuJoCo models against."""
    return make_env(env_id)


def snapshot_env(env_id: str, env: gym.Env) -> dict[str, Any]:
    """Everything needed to continue `env` exactly, as plain data and numpy arrays that tensors can hold (a group's
    checkpoint stores them as tensors); a ValueError naming `env_id` where some of its state cannot be captured."""
    family, _ = split_id(env_id)
    return FAMILIES.get(family)().snapshot(env_id, env)


def restore_env(env_id: str, env: gym.Env, state: dict[str, Any]) -> None:
    """Put `env`, made by `make_env(env_id)` and used or not, into the state `snapshot_env` saved."""
    family, _ = split_id(env_id)
    FAMILIES.get(family)().restore(env_id, env, state)


@dataclass(frozen=True)
class EnvSpaces:
    """An environment's spaces, base-step duration and whether its rows step in parallel in threads
    (`EnvFamily.steps_in_parallel`), read once from a made instance."""

    observation_space: Space
    action_space: Space
    timestep: float | None
    parallel: bool = False

    def problem(self) -> str | None:
        """Why layers cannot control this environment (they need flat Box spaces with finite action bounds)."""
        obs, act = self.observation_space, self.action_space
        if not isinstance(act, Box):
            return f"its action space is {type(act).__name__}; layers need a continuous Box"
        if len(act.shape) != 1 or not (np.all(np.isfinite(act.low)) and np.all(np.isfinite(act.high))):
            return f"its action space {act} is not a vector with finite bounds"
        if not isinstance(obs, Box):
            return f"its observation space is {type(obs).__name__}; layers need a Box"
        return None


@functools.cache
def env_spaces(env_id: str) -> EnvSpaces:
    """The spaces, timestep and parallel steps of a recipe id's environment (made once per process, then closed)."""
    family, name = split_id(env_id)
    source = FAMILIES.get(family)()
    env = source.make(name)
    try:
        return EnvSpaces(env.observation_space, env.action_space, source.timestep(env), source.steps_in_parallel(env))
    finally:
        env.close()


def control_timestep(env_id: str) -> float | None:
    """Seconds of one base step of a recipe id's environment, or None if it defines none."""
    return env_spaces(env_id).timestep


def env_info(env_id: str) -> EnvInfo:
    """Constants of a recipe id; raises KeyError with a readable message for unknown ids."""
    family, name = split_id(env_id)
    return FAMILIES.get(family)().info(name)
