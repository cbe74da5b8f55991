"""Starting and resuming a training run in its directory: checks before anything is written, the
learners, the run directory and its logs, the latest checkpoint; then the loop (layered.trainer),
and the results once every phase is done."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import tomli_w

from layered.events import EventLog
from layered.events import available as events_available
from layered.interrupt import StopRequest
from layered.learner_set import build_learners, keep_start_weights, start_from_weights
from layered.logs import CsvLog
from layered.recipe import Recipe, RecipeError, load_recipe, resolved
from layered.results import EPISODE_FIELDS, metrics_fields, write_results
from layered.learners import Learner
from layered.rundir import (
    RunDirError,
    RunInfo,
    check_new_run_dir,
    has_progress,
    prepare_run_dir,
    read_run_info,
    steps_option,
    writing,
)
from layered.runstate import LoopState, load_state
from layered.trainer import Training, phase_budget, phases_of, train_phases


def warmup_warnings(recipe: Recipe, max_steps: int | None) -> list[str]:
    """Phases too short for a learning layer to finish its random warm-up, so that it never learns."""
    out = []
    periods = {layer.name: recipe.period(i) for i, layer in enumerate(recipe.layers)}
    for p, phase in enumerate(phases_of(recipe)):
        budget = phase_budget(recipe, phase, max_steps)
        for name in phase.learn:
            warmup = recipe.warmup(name)
            if budget <= warmup * periods[name]:
                out.append(f"phase {p} runs {budget} steps, but layer {name!r} acts at random for its first "
                           f"{warmup} decisions ({warmup * periods[name]} steps at period {periods[name]}): "
                           "it will not learn (lower its warmup or raise the steps)")
    return out


def train(
    recipe: Recipe, out_dir: str | Path, max_steps: int | None = None, progress: bool = True,
    label: str | None = None, resume: bool = False, plugins: Sequence[str] = (),
) -> list[dict[str, Any]]:
    """Train every phase of `recipe`, writing the run directory; `max_steps` caps each phase.

    `label` names the setup for reports (e.g. `pendulum/tla-c`); runs of the same setup with
    different seeds share it. It defaults to the run directory's name. With `resume`, a run
    directory holding a stopped run continues from its last checkpoint (an empty one starts);
    without, a directory holding a run is refused. `plugins` (see layered.plugins) are recorded
    so that evaluating the run imports them again. Returns the results row of each phase, as in
    results.json. Raises Stopped when SIGINT or SIGTERM stopped it, after a final checkpoint.
    """
    out = Path(out_dir)
    for warning in warmup_warnings(recipe, max_steps):
        print(f"layered: warning: {warning}", file=sys.stderr)
    unavailable = sorted({p for i in range(len(recipe.layers)) for p in recipe.learner_config(i).unavailable()})
    if unavailable:
        raise RecipeError("recipe", unavailable)
    if recipe.log.tensorboard and not events_available():
        raise RecipeError("recipe", [("log.tensorboard", "needs the extra layered[tensorboard]: "
                                      "pip install -e '.[tensorboard]' in the checkout")])
    info = RunInfo(label or out.name, max_steps, tuple(plugins))
    learners = build_learners(recipe)
    if not (resume and has_progress(out)):
        start_from_weights(recipe, learners)  # a bad `weights` file is refused before anything is written
    if not resume:
        check_new_run_dir(out)  # before the lock creates the directory
    with writing(out):
        return _train_in(out, recipe, learners, info, resume, progress)


def _train_in(out: Path, recipe: Recipe, learners: dict[str, Learner], info: RunInfo, resume: bool,
              progress: bool = True) -> list[dict[str, Any]]:
    """`train`, from the run directory on, while this process holds its lock."""
    max_steps = info.max_steps
    prepare_run_dir(out, tomli_w.dumps(resolved(recipe)), info, resume)  # so that a run killed early resumes
    checkpoint = out / "checkpoints" / "run.pt"
    state = load_state(checkpoint, learners, resolved(recipe), max_steps)
    resumed_at = None if state is None else (state.phase, state.step)
    run = Training(recipe, learners, CsvLog(out / "metrics.csv", metrics_fields(recipe)),
              CsvLog(out / "episodes.csv", EPISODE_FIELDS), checkpoint, max_steps, progress, StopRequest(),
              EventLog(out / "tensorboard", resumed_at) if recipe.log.tensorboard else None)
    if state is None:
        state = LoopState()
        keep_start_weights(recipe, learners, checkpoint.parent)
        run.metrics.start()
        run.episodes.start()
    else:
        run.metrics.truncate(state.log_sizes["metrics"])
        run.episodes.truncate(state.log_sizes["episodes"])
    try:
        train_phases(run, state, out)
    finally:
        if run.events is not None:
            run.events.close()
    write_results(recipe, state.rows, out, info.label)
    return state.rows


def resume(run_dir: str | Path, max_steps: int | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Continue a stopped run from its last checkpoint, with the recipe and settings it was started with.

    `max_steps`, when given, must be the one the run was started with.
    """
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    if info.group:
        raise RunDirError(f"{run_dir}: the run was trained in a group of seeds {list(info.group)}, and a group does "
                          "not checkpoint yet: train the group again with --force")
    if max_steps is not None and max_steps != info.max_steps:
        raise RunDirError(f"{run_dir}: the run was started with {steps_option(info.max_steps)}, not "
                          f"{steps_option(max_steps)}")
    recipe = load_recipe(run_dir / "recipe.toml")
    return train(recipe, run_dir, info.max_steps, progress, info.label, resume=True, plugins=info.plugins)
