"""The registry of environment families and the per-environment constants the metrics need."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import gymnasium as gym

from layered.registry import Registry

DEFAULT_FAMILY = "gym"


@dataclass(frozen=True)
class EnvInfo:
    """Constants of one environment: `return_range` (worst, best) normalises returns for the AUC."""

    return_range: tuple[float, float] | None


class EnvFamily(ABC):
    """A source of environments sharing one naming scheme."""

    @abstractmethod
    def make(self, name: str, render_mode: str | None = None) -> gym.Env:
        """A new Gymnasium env for `name`, with a Box action space and time limit as truncation."""

    @abstractmethod
    def info(self, name: str) -> EnvInfo:
        """Constants of `name`; raises KeyError naming the problem when `name` is unknown."""

    def timestep(self, env: gym.Env) -> float | None:
        """Seconds of one base step of `env`, or None when the environment does not define it."""
        dt = getattr(env.unwrapped, "dt", None)
        return None if dt is None else float(dt)


FAMILIES: Registry[type[EnvFamily]] = Registry("environment family")


def split_id(env_id: str) -> tuple[str, str]:
    """(family, name) of an id such as `dmc:cartpole-swingup`; a bare id is a Gymnasium id."""
    family, sep, name = env_id.partition(":")
    return (family, name) if sep else (DEFAULT_FAMILY, env_id)


def make_env(env_id: str, render_mode: str | None = None) -> gym.Env:
    """A new environment for a recipe id."""
    family, name = split_id(env_id)
    return FAMILIES.get(family)().make(name, render_mode=render_mode)


def control_timestep(env_id: str) -> float | None:
    """Seconds of one base step of a recipe id's environment, or None if it defines none."""
    family, name = split_id(env_id)
    source = FAMILIES.get(family)()
    env = source.make(name)
    try:
        return source.timestep(env)
    finally:
        env.close()


def env_info(env_id: str) -> EnvInfo:
    """Constants of a recipe id; raises KeyError with a readable message for unknown ids."""
    family, name = split_id(env_id)
    return FAMILIES.get(family)().info(name)
