"""The evaluations behind the paper's figures, run on a finished run directory and kept in its
`eval/` folder: the threshold sweep (Fig. 2) and the gallery of states where a layer acts.
`layered eval` writes them anew; `layered report` reuses what is there and runs what is missing."""

from __future__ import annotations

import csv
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from layered.evaluate import evaluation_seed
from layered.learners import Learner
from layered.metrics import Evaluation
from layered.plugins import load_plugins
from layered.recipe import Recipe, load_recipe
from layered.report import DEFAULT_SWEEP, SWEEP_FILE, figure_sweep, kept_episodes, kept_thresholds
from layered.stack import has_threshold
from layered.standing import Standing, standing


def sweep_file(thresholds: list[float], episodes: int | None, own: int) -> str:
    """Where a threshold sweep on `episodes` episodes is kept in a run's eval/ folder: `SWEEP_FILE` for the default
    grid on the run's `own` number of evaluation episodes (or an unknown number, None), and a name of its own for
    any other (`threshold-sweep-0-0.3.csv`, `threshold-sweep-episodes-1.csv`), so that no other sweep stands in for
    the one Fig. 2 is drawn from."""
    parts = ([] if thresholds == DEFAULT_SWEEP else [f"{t:g}" for t in thresholds]) + \
        ([] if episodes in (None, own) else [f"episodes-{episodes}"])
    return "-".join(["threshold-sweep", *parts]) + ".csv"


@dataclass(frozen=True)
class TrainedRun:
    """A run ready to evaluate: its recipe, restored learners, the layers of its stack and the weights asked for
    (None: the recipe's `train.select`); of an unfinished run, where it stands (`layered.standing`); with `fresh`, on
    the episodes of the run's evaluations of its final and best weights on fresh episodes."""

    path: Path
    recipe: Recipe
    learners: dict[str, Learner]
    active: list[str]
    weights: str | None = None
    standing: Standing | None = None
    fresh: bool = False

    @property
    def seed(self) -> int:
        """The evaluation seed, as during training (`fresh`: as at the end of each phase, for the fresh episodes)."""
        return evaluation_seed(self.recipe, self.fresh)

    @property
    def episodes(self) -> int:
        """How many episodes an evaluation plays unless asked otherwise: the recipe's `eval.episodes`, or with `fresh`
        its `eval.fresh_episodes`."""
        return self.recipe.eval.fresh_episodes if self.fresh else self.recipe.eval.episodes

    @property
    def title(self) -> str:
        """What the run's figures name it by: its environment, label and seed."""
        from layered.rundir import read_run_info

        return f"{self.recipe.env.id}, {read_run_info(self.path).label} seed {self.recipe.train.seed}"

    @property
    def eval_dir(self) -> Path:
        """`eval/`, or `eval/weights-<w>/` for weights asked for by name, so that `layered report` reads only
        evaluations of the weights the run hands on; an unfinished run's under `eval/unfinished/`; those on fresh
        episodes under a folder `fresh/` below those."""
        latest = self.weights == "final"
        folder = self.path / "eval" / (self.standing.folder(latest) if self.standing is not None else "")
        folder /= f"weights-{self.weights}" if self.weights else ""
        folder /= "fresh" if self.fresh else ""
        folder.mkdir(parents=True, exist_ok=True)
        return folder


def load_run_plugins(run_dir: Path, given: Sequence[str] = ()) -> None:
    """Import the plugins a run was trained with, and `given` (`--plugin`) first: a plugin file that has moved since
    is found in its new place where `given` names it."""
    from layered.plugins import PluginError, load_plugin
    from layered.rundir import run_plugins

    load_plugins(given)
    for spec in run_plugins(run_dir):
        try:
            load_plugin(spec)
        except PluginError as e:
            if not spec.endswith(".py") or Path(spec).exists():
                raise
            if not given:
                raise PluginError(f"{e} (the run was trained with it: give its new place with --plugin)") from None
            print(f"layered: note: {spec}, a plugin {run_dir} was trained with, is no longer there; using "
                  f"{', '.join(given)} in its place", file=sys.stderr)


def open_run(run_dir: Path, weights: str | None = None, plugins: list[str] | None = None,
             unfinished: bool = False) -> TrainedRun:
    """The run in `run_dir` with its last phase's `final` or `best` weights (default: its train.select; the
    layers of earlier phases as they were handed on), after importing the plugins it was trained with and
    `plugins`. A run that has not finished is refused, or with `unfinished` taken as it stands at its last
    checkpoint: the stack of the phase under way, its learning layers at their best weights so far (`final`: at
    their weights at that checkpoint)."""
    from layered.learner_set import load_learners
    from layered.orders import phases_of
    from layered.rundir import RunDirError, warn_if_being_written, writer

    load_run_plugins(run_dir, plugins or [])  # (refuses a directory that holds no run)
    recipe = load_recipe(run_dir / "recipe.toml")
    if (run_dir / "results.json").exists():
        warn_if_being_written(run_dir)
        return TrainedRun(run_dir, recipe, load_learners(recipe, run_dir, weights), list(phases_of(recipe)[-1].active),
                          weights)
    at = standing(run_dir, recipe.train.seed)
    where = "at its last checkpoint " + (f"phase {at.phase} was at step {at.step}" if at.best
                                          else f"phase {at.stack_phase} had ended")
    if not unfinished:
        going = "let it finish" if writer(run_dir) else f"`layered resume {run_dir}` finishes it"
        raise RunDirError(f"{run_dir} has not finished ({where}): {going}, then try again; `layered eval {run_dir}` "
                          "evaluates its best weights so far")
    phase = phases_of(recipe)[at.stack_phase]
    holder = writer(run_dir)
    state = f"is being trained by {holder}" if holder else "has stopped"
    learning = ", ".join(repr(name) for name in phase.learn)
    if not at.best:
        chosen, under_way = "every layer as that phase handed it on", {}
    elif weights == "final":
        chosen, under_way = f"{learning} at its weights there", _latest_weights(recipe, at)
    else:
        chosen, under_way = (f"{learning} at the best weights so far (evaluated at step {at.best_step}: return "
                             f"{at.best_return:.1f})"), at.best
    print(f"layered: note: {run_dir} {state}: {where}; evaluating {chosen}", file=sys.stderr)
    return TrainedRun(run_dir, recipe, load_learners(recipe, run_dir, weights, at.stack_phase, under_way),
                      list(phase.active), weights, at)


def open_group(directory: Path, weights: str | None = None, plugins: list[str] | None = None,
               fresh: bool = False) -> list[TrainedRun]:
    """The seeds of the group in `directory`, each opened as `open_run` opens a run (an unfinished group as it stands
    at its last checkpoint), with `fresh` on their fresh episodes."""
    from layered.group_state import group_info, seed_dirs
    from layered.rundir import RunDirError

    runs = [replace(open_run(out, weights, plugins, unfinished=True), fresh=fresh)
            for out in seed_dirs(directory, group_info(directory).group)]
    stacks = {run.path.name: "+".join(run.active) for run in runs}
    if len(set(stacks.values())) > 1:
        raise RunDirError(f"{directory}: its seeds stand at different stacks ({stacks}), while a group's seeds "
                          "train the same phases together")
    return runs


def evaluate_group_runs(runs: list[TrainedRun], episodes: int, threshold: float | None = None,
                        progress: bool = False) -> list[Evaluation]:
    """Each of a group's seeds (`open_group`) evaluated over `episodes` episodes as the group's own evaluations are:
    the seeds' learners stacked (`layered.group.stack_learners`) and their episodes played side by side, so that the
    numbers are those training wrote, in the last digit too (where an actor settles, exact repetition depends on
    how the products were summed: metrics.md)."""
    from layered.group import stack_learners
    from layered.group_eval import close_evaluator, evaluate_seeds, open_group_evaluator

    first = runs[0]
    stacked = stack_learners([run.recipe for run in runs], [run.learners for run in runs])
    evaluator = open_group_evaluator(first.recipe, first.active, episodes, len(runs), threshold)
    try:
        return evaluate_seeds(evaluator, stacked, episodes, [run.seed for run in runs], progress)
    finally:
        close_evaluator(evaluator)


def _latest_weights(recipe: Recipe, at: Standing) -> dict[str, dict[str, Any]]:
    """The weights of the learning layers of an unfinished run (or group seed) at its last checkpoint."""
    from layered.group import seed_weights
    from layered.learner_set import resumed_weights

    if at.row is None:
        return resumed_weights(recipe, at.latest)
    return seed_weights(recipe, at.latest, at.row, at.rows)


def evaluate_trained(run: TrainedRun, episodes: int | None = None, threshold: float | None = None,
                     progress: bool = False) -> Evaluation:
    """`run` evaluated over `episodes` episodes (default: its count), side by side as its training's evaluations
    are, at the recipe's thresholds or `threshold`: what `layered eval RUN` measures."""
    from layered.group_eval import close_evaluator, evaluate_run, open_run_evaluator

    episodes = episodes or run.episodes
    evaluator = open_run_evaluator(run.recipe, run.active, episodes, threshold)
    try:
        return evaluate_run(evaluator, run.learners, episodes, run.seed, progress=progress)
    finally:
        close_evaluator(evaluator)


def eval_run(run_dir: str | Path, episodes: int | None = None, weights: str | None = None,
             threshold: float | None = None, fresh: bool = False, threads: int | None = None) -> Evaluation:
    """`layered eval RUN` from Python: the run in `run_dir` (finished, or as it stands at its last checkpoint) with
    its `final` or `best` weights (default: its train.select), over `episodes` of its evaluation's episodes or,
    with `fresh`, of the fresh ones its phases ended on, computed with `threads` torch threads (default: those it
    trained with, as the command does); the measures (`Evaluation`: return, repetition, decisions, ...). Nothing
    is written, and the process's thread count is as before afterwards."""
    from layered.cores import torch_threads, trained_threads
    from layered.rundir import read_run_info

    run = replace(open_run(Path(run_dir), weights, unfinished=True), fresh=fresh)
    with torch_threads(threads or trained_threads(read_run_info(Path(run_dir)).threads)):
        return evaluate_trained(run, episodes, threshold)


def threshold_sweep(run: TrainedRun, thresholds: list[float], episodes: int | None = None
                    ) -> tuple[list[dict[str, Any]], Path]:
    """One evaluation per threshold (a fraction of the maximum action), its episodes side by side: the paper's
    return and action frequency against the threshold (Fig. 2). Writes eval/`sweep_file(...)`; its rows, and that
    file."""
    from tqdm import tqdm

    from layered.group_eval import evaluate_run, open_run_envs, stacks_over

    episodes = episodes or run.recipe.eval.episodes
    rows = []
    envs = open_run_envs(run.recipe, episodes)
    try:
        for threshold in tqdm(thresholds, desc="threshold sweep", unit="threshold"):
            at = stacks_over(run.recipe, run.active, envs, evaluation=True, threshold=threshold)
            rows.append({"threshold": threshold, "episodes": episodes,
                         **evaluate_run(at, run.learners, episodes, run.seed).row()})
    finally:
        envs.close()
    path = run.eval_dir / sweep_file(thresholds, episodes, run.recipe.eval.episodes)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return rows, path


def gallery(run: TrainedRun, layer: str, episodes: int | None = None, threshold: float | None = None
            ) -> tuple[Path, int, int, int]:
    """Render the most different states where `layer` acts in `layered eval`'s episodes (default: the run's count)
    into eval/gallery-LAYER.png; the file, the steps at which the layer acted, of how many, and the number of
    states shown."""
    from layered.evaluate import states_where_layer_acts
    from layered.report import save_gallery

    acted, steps, shots = states_where_layer_acts(run.recipe, run.learners, run.active, layer, run.seed,
                                                  episodes or run.episodes, threshold)
    png = run.eval_dir / f"gallery-{layer}.png"
    save_gallery(shots, layer, png, f"{run.title}: {len(shots)} of the {acted} steps (of {steps}) where layer "
                 f"{layer!r} changed the action, the most different")
    return png, acted, steps, len(shots)


def missing_figure_evals(run_dir: Path) -> list[str]:
    """What `layered report` would evaluate for this run: a threshold sweep where a threshold
    applies and none is kept, a gallery of the fastest layer where a stack has several layers."""
    from layered.orders import phases_of

    load_run_plugins(run_dir)  # (its recipe may name what they register)
    recipe = load_recipe(run_dir / "recipe.toml")
    missing = []
    if has_threshold(recipe, phases_of(recipe)[-1].active) and not figure_sweep(run_dir / "eval" / SWEEP_FILE,
                                                                                  recipe.eval.episodes):
        missing.append("threshold sweep")
    if len(recipe.layers) > 1 and not (run_dir / "eval" / f"gallery-{recipe.layers[-1].name}.png").exists():
        missing.append("gallery")
    return missing


def run_figure_evals(run_dir: Path, missing: list[str]) -> None:
    """Run the evaluations `missing_figure_evals` named for this run."""
    run = open_run(run_dir)
    if "threshold sweep" in missing:
        kept = run.eval_dir / SWEEP_FILE
        if kept.exists():  # another sweep, kept there before it had a name of its own: moved to it (one of unknown
            # episodes over the default grid is evaluated again in its place)
            renamed = run.eval_dir / sweep_file(kept_thresholds(kept), kept_episodes(kept), run.recipe.eval.episodes)
            if renamed != kept:
                kept.rename(renamed)
                if kept.with_suffix(".png").exists():
                    kept.with_suffix(".png").rename(renamed.with_suffix(".png"))
        threshold_sweep(run, DEFAULT_SWEEP)
    if "gallery" in missing:
        gallery(run, run.active[-1])
