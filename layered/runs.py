"""Starting and resuming a training run in its directory: checks before anything is written, the
learners, the run directory and its logs, the latest checkpoint; then the loop (layered.trainer),
and the results once every phase is done."""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w
import torch

from layered.checkpoint import CheckpointError
from layered.combiners import COMBINERS
from layered.errors import Diverged
from layered.events import available as events_available
from layered.interrupt import StopRequest
from layered.learner_set import build_learners, keep_start_weights, precisions, start_from_weights
from layered.recipe import Recipe, RecipeError, load_recipe, resolved
from layered.results import write_results
from layered.run_logs import RunLogs
from layered.learners import Learner
from layered.orders import phases_of
from layered.rundir import (
    RUN_CHECKPOINT,
    RunDirError,
    RunInfo,
    check_new_run_dir,
    check_same_steps,
    clear_run_dir,
    has_progress,
    no_checkpoint_to_change,
    prepare_run_dir,
    read_run_info,
    record_change,
    refuse_group_seed,
    writing,
)
from layered.replay_journal import ReplayJournal, replay_folder
from layered.runstate import LoopState, load_state, recipe_differences, recipe_digest
from layered.trainer import Training, phase_budget, train_phases


CHANGEABLE = re.compile(r"layers\[\d+\]\.(learner\.(?!kind$)\w+|action_penalty|updates)$|env\.(workers|threads|wait)$")
"""The resolved recipe's keys a resumed run may change (`layered resume --set`): a layer's learning, and where and how
a group's environments step, which changes no number (a group moved to a machine with other cores)."""
GROUP_ONLY = ("env.workers", "env.wait")
"""Of those, the keys that change nothing in a single run: it steps its environment in its own process."""


def group_only_settings(recipe: Recipe) -> list[str]:
    """`GROUP_ONLY` settings a recipe gives a single run, where they change nothing (said, not refused: a recipe may
    be written for groups and also trained alone)."""
    given = [key for key in GROUP_ONLY if getattr(recipe.env, key.partition(".")[2]) != "auto"]
    return [f"{' and '.join(given)} set how a group's environments step (layered train --seeds); a single run steps "
            "its environment in its own process, so they change nothing here"] if given else []


def unavailable_settings(recipe: Recipe) -> list[tuple[str, str]]:
    """The recipe's settings this machine cannot honour (a device, a compiler, TensorBoard), as (key, why)."""
    out = sorted({p for i in range(len(recipe.layers)) for p in recipe.learner_config(i).unavailable()})
    if recipe.log.tensorboard and not events_available():
        out.append(("log.tensorboard", "needs the extra layered-control[tensorboard]: "
                                       "pip install -e '.[tensorboard]' in the checkout"))
    return out


def training_warnings(recipe: Recipe, max_steps: int | None) -> list[str]:
    """What in the recipe trains a layer in vain: a phase too short for its warm-up, a gate that never learns."""
    return warmup_warnings(recipe, max_steps) + untrained_gates(recipe)


def untrained_gates(recipe: Recipe) -> list[str]:
    """Gates that route the layers below them but never learn to: a gate layer's gate output is used only where a
    layer below it is present (the fastest present layer's output just joins the sum), so one trained only alone
    routes the layers below it by its initial weights."""
    names, phases, out = recipe.layer_names(), phases_of(recipe), []
    for i, name in enumerate(names):
        kind = recipe.combiner_kind(i)
        if kind is None or not COMBINERS.get(kind).gate_dims:
            continue
        below = set(names[i + 1:])
        routing = [p for p, phase in enumerate(phases) if name in phase.active and below & set(phase.active)]
        if routing and not any(name in phases[p].learn for p in routing):
            out.append(f"layer {name!r} gates the layers below it ({kind!r}) from phase {routing[0]} on, but learns "
                       "in no phase where one of them is present: its gate output, unused while it learns alone, "
                       "routes them by its initial weights (train it over a layer below: order \"fast-to-slow\", "
                       "\"joint\" or explicit phases)")
    return out


def warmup_warnings(recipe: Recipe, max_steps: int | None) -> list[str]:
    """Phases too short for a learning layer to finish its random warm-up, so that it never learns."""
    out = []
    periods = {layer.name: recipe.period(i) for i, layer in enumerate(recipe.layers)}
    for p, phase in enumerate(phases_of(recipe)):
        budget = phase_budget(recipe, phase, max_steps)
        for name in phase.learn:
            warmup = recipe.warmup(name)
            if budget <= warmup * periods[name]:
                own = recipe.layers[recipe.layer_names().index(name)].warmup is not None
                key = f"layers.{name}.warmup" if own else "train.warmup"  # (a layer's own takes train.warmup's place)
                out.append(f"phase {p} runs {budget} steps, but layer {name!r} acts at random for its first "
                           f"{warmup} decisions ({warmup * periods[name]} steps at period {periods[name]}): "
                           f"it will not learn (lower {key} or raise the steps)")
    return out


@dataclass(frozen=True)
class Change:
    """Settings changed on resuming a run: the recipe its checkpoint was made with, and the `key=value`s."""

    before: Recipe
    settings: tuple[str, ...]
    differences: tuple[str, ...]  # `key: before -> after` of each changed value


def train(
    recipe: Recipe, out_dir: str | Path, max_steps: int | None = None, progress: bool = True,
    label: str | None = None, resume: bool = False, plugins: Sequence[str] = (), change: Change | None = None,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Train every phase of `recipe`, writing the run directory; `max_steps` caps each phase.

    `label` names the setup for reports (e.g. `pendulum/tla-c`); runs of the same setup with
    different seeds share it. It defaults to the run directory's name. With `resume`, a run
    directory holding a stopped run continues from its last checkpoint (an empty one starts); without, a directory
    holding a run is refused, or with `force` cleared once the recipe, its settings and its start weights have been
    checked (never a seed of a group, nor a directory holding other files). `plugins` (see layered.plugins) are
    recorded so that evaluating the run imports them again. `change` (with `resume`): `recipe` is the run's own
    with some settings changed, recorded in run.json at the step it continues from. Returns the
    results row of each phase, as in results.json. Raises Stopped when SIGINT or SIGTERM stopped it,
    after a final checkpoint.
    """
    out = Path(out_dir)
    unavailable = unavailable_settings(recipe)
    if unavailable:
        raise RecipeError(RecipeError.UNNAMED, unavailable)
    for warning in training_warnings(recipe, max_steps) + group_only_settings(recipe):
        print(f"layered: warning: {warning}", file=sys.stderr)
    info = RunInfo(label or out.name, max_steps, tuple(plugins), threads=torch.get_num_threads())
    learners = build_learners(recipe)
    if not (resume and has_progress(out)):
        start_from_weights(recipe, learners)  # a bad `weights` file is refused before anything is written
    if not resume:
        refuse_group_seed(out)
        if force and out.is_dir():  # (once the recipe, its settings and its start weights have been checked)
            clear_run_dir(out)
        check_new_run_dir(out)  # before the lock creates the directory
    with writing(out):
        return _train_in(out, recipe, learners, info, resume, progress, change)


def _train_in(out: Path, recipe: Recipe, learners: dict[str, Learner], info: RunInfo, resume: bool,
              progress: bool = True, change: Change | None = None) -> list[dict[str, Any]]:
    """`train`, from the run directory on, while this process holds its lock."""
    max_steps = info.max_steps
    # (written before anything else, so that a run killed early resumes)
    prepare_run_dir(out, tomli_w.dumps(resolved(recipe)), info, resume, precisions(learners))
    checkpoint = out / RUN_CHECKPOINT
    previous = changed_from(out, change) if resume else None
    journal = ReplayJournal(replay_folder(checkpoint))
    try:
        state = load_state(checkpoint, learners, resolved(recipe), max_steps, journal, previous)
    except CheckpointError:
        raise
    except (RuntimeError, KeyError, ValueError) as e:  # a changed setting the networks cannot take
        if change is None:
            raise
        raise misfit(out, e) from None
    if change is not None:
        if state is None:
            raise no_checkpoint_to_change(out)
        record(out, recipe, change, previous, state.phase, state.step)
    resumed_at = None if state is None else (state.phase, state.step)
    run = Training(recipe, learners, RunLogs.open(out, recipe, resumed_at), checkpoint, max_steps, progress,
                   StopRequest(), journal)
    if state is None:
        state = LoopState()
        keep_start_weights(recipe, learners, checkpoint.parent)
        run.logs.begin()
    else:
        run.logs.begin(state.log_sizes)
    with run.stop.installed():  # (until the results are written: a signal after the last step lets them finish)
        try:
            train_phases(run, state, out)
        except Diverged as e:
            raise Diverged(f"{e}; {way_on(out, recipe, e.layer, has_progress(out))}", e.layer) from None
        finally:
            run.logs.close()
        write_results(recipe, state.rows, out, info.label)
    return state.rows


def way_on(out: Path, recipe: Recipe, layer: str | None, checkpointed: bool) -> str:
    """What to do after a divergence in the run (or group) in `out`: from its last checkpoint, if it has one
    (`checkpointed`), with a lower learning rate."""
    if layer is None:
        return "check the environment"
    config = recipe.learner_config(recipe.layer_names().index(layer))
    lower = f"layers.{layer}.learner.lr={getattr(config, 'lr', 3e-4) / 3:.3g}"
    if checkpointed:
        return f"the last checkpoint is intact: continue from it with a lower learning rate, `layered resume {out} " \
               f"--set {lower}`"
    return f"no checkpoint was taken before it: train again with --force and a lower learning rate ({lower})"


def resume(run_dir: str | Path, max_steps: int | None = None, progress: bool = True,
           settings: Sequence[str] = ()) -> list[dict[str, Any]]:
    """Continue a stopped run from its last checkpoint, with the recipe and settings it was started with,
    or with the `key=value` `settings` changed (a layer's learner settings but its kind, action
    penalty and updates per decision: the way on after a divergence), recorded in run.json.

    `max_steps`, when given, must be the one the run was started with.
    """
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    if info.group:
        raise RunDirError(f"{run_dir}: the run trains in a group of seeds {list(info.group)}; continue the group "
                          f"with `layered resume {run_dir.parent}`")
    check_same_steps(run_dir, info.max_steps, max_steps)
    recipe, change = changed_recipe(run_dir, settings) if settings else (load_recipe(run_dir / "recipe.toml"), None)
    if change is not None and (inert := [d.split(":")[0] for d in change.differences
                                         if d.split(":")[0] in GROUP_ONLY]):
        raise RunDirError(f"{run_dir}: a single run steps its environment in its own process, so {' and '.join(inert)} "
                          "change nothing in it (they set how a group's environments step)")
    return train(recipe, run_dir, info.max_steps, progress, info.label, resume=True, plugins=info.plugins,
                 change=change)


def changed_recipe(run_dir: Path, settings: Sequence[str], where: Path | None = None) -> tuple[Recipe, Change]:
    """The recipe of the run in `run_dir` with the `key=value` `settings` changed, and the change; refused (naming
    `where`, default the run) when they change nothing or what a resumed run may not change (see CHANGEABLE)."""
    where = where or run_dir
    before, recipe = load_recipe(run_dir / "recipe.toml"), load_recipe(run_dir / "recipe.toml", settings)
    differences = recipe_differences(resolved(before), resolved(recipe))
    if not differences:
        raise RunDirError(f"{where}: --set {' '.join(settings)} changes nothing")
    fixed = [d.split(":")[0] for d in differences if not CHANGEABLE.match(d.split(":")[0])]
    if fixed:
        raise RunDirError(f"{where}: a resumed run may change a layer's learner settings (not its kind), "
                          f"action_penalty and updates, and how a group's environments step (env.workers, env.threads, "
                          f"env.wait), not {', '.join(fixed)}")
    return recipe, Change(before, tuple(settings), tuple(differences))


def misfit(where: Path, error: Exception) -> RunDirError:
    """The error for a checkpoint that the learners, built with changed settings, could not load."""
    return RunDirError(f"{where}: the checkpoint does not fit the changed settings "
                       f"({str(error).strip().splitlines()[0][:200]})")


def changed_from(run_dir: Path, change: Change | None) -> str | None:
    """The digest of the recipe that the run's checkpoints may have been taken with besides its own: the one
    before `change` (being made now), or before the last change recorded in run.json (one made after its
    newest checkpoint)."""
    if change is not None:
        return recipe_digest(resolved(change.before))
    if not (run_dir / "run.json").exists():
        return None
    changes = read_run_info(run_dir).changes
    return changes[-1]["from"] if changes else None


def record(run_dir: Path, recipe: Recipe, change: Change, from_digest: str | None, phase: int, step: int) -> None:
    """Make the changed `recipe` the run's, recording `change` in run.json as applying from `phase` and `step`."""
    record_change(run_dir, tomli_w.dumps(resolved(recipe)), {
        "phase": phase, "step": step, "set": list(change.settings), "from": from_digest,
        "differences": list(change.differences)})
