"""Environment families behind one id scheme, `family:name` (the family defaults to `gym`)."""

from layered.envs.rendering import RenderingUnavailable, choose_backend

choose_backend()  # MuJoCo's GL backend, before any family imports MuJoCo

# ruff: noqa: E402  (the families import MuJoCo, which reads the backend on import)
from layered.envs import dm_control_family as _dm_control_family  # noqa: F401  (registers "dmc")
from layered.envs import gymnasium_family as _gymnasium_family  # noqa: F401  (registers "gym")
from layered.envs import robotics_family as _robotics_family  # noqa: F401  (registers "robotics")
from layered.envs.registry import (
    FAMILIES,
    EnvFamily,
    EnvInfo,
    EnvSpaces,
    control_timestep,
    env_info,
    env_spaces,
    make_env,
    restore_env,
    snapshot_env,
    split_id,
)

__all__ = [
    "FAMILIES", "EnvFamily", "EnvInfo", "EnvSpaces", "RenderingUnavailable", "control_timestep", "env_info",
    "env_spaces", "make_env", "restore_env", "snapshot_env", "split_id",
]
