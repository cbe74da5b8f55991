"""layered: reinforcement-learning control with stacks of controllers acting at several timescales.

The names below are imported when first used, so that importing the package (as the `layered`
command does before anything else) loads neither torch nor the environments.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from layered.agents import LayeredEnv, make_aec_env
    from layered.errors import BadInput, Diverged
    from layered.plugins import load_plugin
    from layered.recipe import Recipe, RecipeError, load_recipe
    from layered.run_evals import eval_run
    from layered.runs import resume, train

_HOMES = {"LayeredEnv": "layered.agents", "make_aec_env": "layered.agents", "BadInput": "layered.errors",
          "Diverged": "layered.errors", "load_plugin": "layered.plugins",
          "Recipe": "layered.recipe", "RecipeError": "layered.recipe", "load_recipe": "layered.recipe",
          "resume": "layered.runs", "train": "layered.runs", "eval_run": "layered.run_evals"}
__all__ = ["BadInput", "Diverged", "LayeredEnv", "Recipe", "RecipeError", "eval_run", "load_plugin", "load_recipe",
           "make_aec_env", "resume", "train"]
__version__ = "0.1.0"


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'layered' has no attribute {name!r}")
    return getattr(importlib.import_module(_HOMES[name]), name)
