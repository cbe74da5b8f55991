"""layered: reinforcement-learning control with stacks of controllers acting at several timescales."""

from layered.agents import LayeredEnv, make_aec_env
from layered.plugins import load_plugin
from layered.recipe import Recipe, RecipeError, load_recipe
from layered.runs import resume, train

__all__ = ["LayeredEnv", "Recipe", "RecipeError", "load_plugin", "load_recipe", "make_aec_env", "resume", "train"]
__version__ = "0.1.0"
