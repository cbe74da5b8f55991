"""Environment families behind one id scheme, `family:name` (the family defaults to `gym`)."""

from layered.envs import gymnasium_family as _gymnasium_family  # noqa: F401  (registers "gym")
from layered.envs.registry import FAMILIES, EnvFamily, EnvInfo, env_info, make_env, split_id

__all__ = ["FAMILIES", "EnvFamily", "EnvInfo", "env_info", "make_env", "split_id"]
