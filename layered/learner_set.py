"""A recipe's learners, one per layer: built new, started from the weights a recipe names, or restored
from a run's checkpoints."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from layered.agents import make_aec_env
from layered.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from layered.learners import LEARNERS, Learner
from layered.learners.base import check_plugin_learner, is_plugin
from layered.orders import phases_of, stack_weights
from layered.schema import SEED, Recipe, RecipeError


def build_learners(recipe: Recipe, device: str | None = None) -> dict[str, Learner]:
    """One new learner per layer, each with its own seed, on the spaces of the whole stack;
    `device` replaces the recipe's `device` setting of the learners that have one."""
    torch.manual_seed(recipe.train.seed)
    env = make_aec_env(recipe)
    learners = {}
    for i, layer in enumerate(recipe.layers):
        config = recipe.learner_config(i)
        if device is not None:
            config = config.on_device(device)
        space = env.action_space(layer.name)
        layout = recipe.output_layout(i, env.stack.action_dim)
        seed = recipe.train.seed * 1000 + i
        learners[layer.name] = LEARNERS.get(config.kind)(env.observation_space(layer.name), space, layout, config, seed)
        if is_plugin(learners[layer.name]):
            check_plugin_learner(learners[layer.name], layer.name)
    env.close()
    return learners


def load_learners(recipe: Recipe, run_dir: Path, weights: str | None = None, phase: int = -1,
                  under_way: Mapping[str, dict[str, Any]] | None = None) -> dict[str, Learner]:
    """The learners of a run, restored from its checkpoints as phase `phase` (by default its last) ends: the
    layers that learn in that phase at their `final` or `best` weights (default: the recipe's `train.select`), the
    others at those their phase handed on (`orders.stack_weights`). Of a phase under way, the layers it learns
    at their weights in `under_way` and only the layers it has present. They act on the CPU, fastest for one
    observation at a time, so a run trained on a GPU evaluates anywhere."""
    learners = build_learners(recipe, device="cpu")
    chosen = stack_weights(recipe, weights, phase)
    present = recipe.layer_names() if under_way is None else phases_of(recipe)[phase].active
    for name in present:
        if under_way is not None and name in under_way:
            learners[name].load_state_dict(under_way[name])
            continue
        learners[name].load_state_dict(load_checkpoint(layer_checkpoint(run_dir / "checkpoints", name, chosen[name]),
                                                       name))
    return learners


def resumed_weights(recipe: Recipe, states: Mapping[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The weights (`state_dict`s) that layers' learner states `states`, as a run's checkpoint holds them (what
    `resume_state` returned), hold."""
    learners = build_learners(recipe, device="cpu")
    for name, state in states.items():
        learners[name].load_resume_state(state)
    return {name: learners[name].state_dict() for name in states}


def start_from_weights(recipe: Recipe, learners: dict[str, Learner]) -> None:
    """Load each layer's `weights` checkpoint (`{seed}` in its path: the recipe's seed) into its learner; a file
    that is missing, unreadable, of another layer or of other network sizes is refused, naming the layer."""
    problems = []
    for i, layer in enumerate(recipe.layers):
        if layer.weights is None:
            continue
        path = Path(layer.weights.replace(SEED, str(recipe.train.seed)))
        try:
            learners[layer.name].load_state_dict(load_checkpoint(path, layer.name))
        except CheckpointError as e:
            problems.append((f"layers[{i}].weights", str(e)))
        except (RuntimeError, KeyError, ValueError) as e:
            problems.append((f"layers[{i}].weights", f"{path}: does not fit layer {layer.name!r}'s "
                             f"learner ({str(e).strip().splitlines()[0]})"))
    if problems:
        raise RecipeError(RecipeError.UNNAMED, problems)


def precisions(learners: Mapping[str, Learner]) -> dict[str, str]:
    """What each layer's updates compute in (`Learner.computes_in`), as its run.json records it."""
    return {name: learner.computes_in() for name, learner in learners.items()}


def layer_checkpoint(folder: Path, name: str, weights: str) -> Path:
    """Where a run's checkpoints folder keeps layer `name`'s `final` or `best` weights (of the last phase that
    trained it)."""
    return folder / f"{name}{'.best' if weights == 'best' else ''}.pt"


def save_layer_weights(folder: Path, name: str, final: dict[str, Any], best: dict[str, Any]) -> None:
    """Keep layer `name`'s final and best weights (`state_dict`s) in a run's checkpoints folder."""
    for weights, state in (("final", final), ("best", best)):
        save_checkpoint(layer_checkpoint(folder, name, weights), name, state)


def keep_start_weights(recipe: Recipe, learners: dict[str, Learner], folder: Path) -> None:
    """Copy the start weights into the run's checkpoints as the layer's final and best, so that the
    run evaluates without the original file (a phase that trains the layer replaces them)."""
    for layer in recipe.layers:
        if layer.weights is not None:
            weights = learners[layer.name].state_dict()
            save_layer_weights(folder, layer.name, weights, weights)
