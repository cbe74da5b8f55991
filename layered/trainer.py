"""The training loop: phases of a training order, each driving the stack's AEC env directly.

The loop's position is one `LoopState`, checkpointed with the learners at episode boundaries
(see layered.runstate), so that a run stopped at any moment resumes to exactly the result of a run
that never stopped; SIGINT and SIGTERM finish the episode under way, checkpoint and stop. Starting
and resuming a run in its directory is layered.runs.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from layered.agents import LayeredEnv, make_aec_env
from layered.learner_set import save_layer_weights
from layered.evaluate import evaluation_seed
from layered.group_eval import Stacks, close_evaluator, evaluate_run, open_run_evaluator
from layered.interrupt import StopRequest, Stopped
from layered.learners import Learner
from layered.learners.base import checked_losses, is_plugin
from layered.errors import Diverged
from layered.metrics import Evaluation, normalised_auc
from layered.orders import Phase, phases_of
from layered.progress import Progress
from layered.recipe import Recipe, resolved
from layered.replay_journal import ReplayJournal
from layered.results import mean_losses, write_finished_phases
from layered.run_logs import RunLogs
from layered.runstate import LoopState, save_state

FRESH_MEASURES = ("return_mean", "return_std", "repetition", "repetition_at_bounds", "repetition_held", "decisions",
                  "jerk")


@dataclass(frozen=True)
class PhaseResult:
    """The outcome of one phase: its final evaluation and the AUC of its evaluation curve."""

    index: int
    phase: Phase
    steps: int
    final: Evaluation
    auc: float | None


@dataclass(frozen=True)
class Training:
    """What stays fixed while a run trains: its recipe, learners, logs and where it checkpoints."""

    recipe: Recipe
    learners: dict[str, Learner]
    logs: RunLogs
    checkpoint: Path
    max_steps: int | None
    progress: bool
    stop: StopRequest
    journal: ReplayJournal  # the replay buffers' segments

    def save(self, state: LoopState) -> None:
        """Checkpoint the whole training state, with how much of each log it covers."""
        state.log_sizes = self.logs.sizes()
        save_state(self.checkpoint, state, self.learners, resolved(self.recipe), self.max_steps, self.journal)


def phase_budget(recipe: Recipe, phase: Phase, max_steps: int | None) -> int:
    """Base environment steps of a phase: its own, or `train.steps_per_phase`, capped at `max_steps`."""
    return min(phase.steps or recipe.train.steps_per_phase, max_steps or np.iinfo(np.int64).max)


def checkpoint_interval(recipe: Recipe) -> int:
    """Environment steps between checkpoints (each taken at the next episode end): by default, one per evaluation."""
    return recipe.train.checkpoint_every or recipe.eval.every


def train_phases(run: Training, state: LoopState, out: Path) -> None:
    """Train the phases from where `state` stands, checkpointing at the end of each (SIGINT and SIGTERM handled by
    `run.stop`, installed by the caller)."""
    recipe = run.recipe
    phases = phases_of(recipe)
    if state.rows:  # (resumed: written again for a run whose file is missing, from before it was kept)
        write_finished_phases(state.rows, out)
    for p in range(len(state.rows), len(phases)):
        if not state.curve:  # the phase starts now, rather than resuming from a checkpoint inside it
            state.start_phase(p, phases[p].learn, recipe.eval.every, checkpoint_interval(recipe))
        result = run_phase(run, state, phases[p], phase_budget(recipe, phases[p], run.max_steps))
        if p == len(phases) - 1:
            run.stop.finishing()
        state.finish_phase(_finish_phase(run, state, phases[p], result))
        write_finished_phases(state.rows, out)  # (before the checkpoint: a phase finished again writes it again)
        run.save(state)
        if run.stop.requested and p < len(phases) - 1:
            raise Stopped(run.stop.requested, p + 1, 0, out)


def _finish_phase(run: Training, state: LoopState, phase: Phase, result: PhaseResult) -> dict[str, Any]:
    """Save the phase's final and best weights, evaluate both on fresh episodes, and leave the
    learners holding the ones `train.select` hands on; the phase's results row."""
    recipe, learners, folder = run.recipe, run.learners, run.checkpoint.parent
    keep_final = recipe.train.select == "final"
    final = {name: copy.deepcopy(learners[name].state_dict()) for name in phase.learn} if keep_final else {}
    for name in phase.learn:
        save_layer_weights(folder, name, learners[name].state_dict(), state.best[name])
    row = phase_row(result, state)
    evaluator = open_run_evaluator(recipe, phase.active, recipe.eval.fresh_episodes) if recipe.eval.fresh_episodes \
        else None
    try:
        row |= _fresh_evaluation(run, evaluator, "final")  # the learners hold the final weights
        for name in phase.learn:
            learners[name].load_state_dict(state.best[name])
        row |= _fresh_evaluation(run, evaluator, "best")
    finally:
        if evaluator is not None:
            close_evaluator(evaluator)
    for name in final:
        learners[name].load_state_dict(final[name])
    return row


def _fresh_evaluation(run: Training, evaluator: Stacks | None, label: str) -> dict[str, float]:
    """The present layers evaluated on `eval.fresh_episodes` episodes of their own seed, as
    `fresh_<label>_<measure>` (nothing without an evaluator: eval.fresh_episodes is 0)."""
    if evaluator is None:
        return {}
    recipe = run.recipe
    result = evaluate_run(evaluator, run.learners, recipe.eval.fresh_episodes, evaluation_seed(recipe, fresh=True))
    return fresh_row(label, result)


def run_phase(run: Training, state: LoopState, phase: Phase, budget: int) -> PhaseResult:
    """Train `phase.learn` for `budget` base steps with the other present layers frozen, from `state`.

    Learning layers act at random for their first `warmup` decisions, then with
    exploration noise, and update once per decision after that; frozen layers act greedily.
    """
    recipe = run.recipe
    env = make_aec_env(recipe, active=list(phase.active))
    evaluator = open_run_evaluator(recipe, phase.active, recipe.eval.episodes)
    bar = Progress(f"phase {state.phase}: {'+'.join(phase.learn)}", budget, state.step, run.progress,
                   later=len(phases_of(recipe)) - 1 - state.phase)
    try:
        if not state.curve:
            _evaluate(run, state, phase, evaluator, bar)
        while state.step < budget:
            _start_episode(env, state, recipe)
            _train_episode(run, state, phase, budget, env, evaluator, bar)
            _end_episode(run, env, state)
        if state.curve[-1][0] != state.step:
            _evaluate(run, state, phase, evaluator, bar)
    finally:
        bar.close()
        env.close()
        close_evaluator(evaluator)
    return PhaseResult(state.phase, phase, state.step, state.curve[-1][1], curve_auc(recipe, state.curve))


def _train_episode(run: Training, state: LoopState, phase: Phase, budget: int, env: LayeredEnv, evaluator: Stacks,
                   bar: Progress) -> None:
    """One training episode, or its part until the phase's budget is spent: per decision of a
    layer, store its completed transition, act, step the env, update, log."""
    learners, recipe = run.learners, run.recipe
    warmups = {name: recipe.warmup(name) for name in phase.learn}
    checked = {name: is_plugin(learners[name]) for name in phase.learn}  # (a plugin's losses: the shipped are tested)
    updates = {layer.name: layer.updates for layer in recipe.layers}
    for name in env.agent_iter():
        obs, _, terminated, truncated, info = env.last()
        learner, learns = learners[name], name in phase.learn
        _check_finite(obs, "observation", name, state)
        if learns and "transition" in info:
            learner.observe(info["transition"])  # store
        if terminated or truncated:
            env.step(None)
            continue
        if state.step >= budget:
            return
        if not learns:  # act
            action = learner.act(obs, explore=False)
        else:
            warm = state.decisions[name] < warmups[name]
            action = learner.random_action() if warm else learner.act(obs, explore=True)
        _check_finite(action, "action", name, state)
        before = env.episode_steps
        env.step(action)  # step
        advanced = env.episode_steps - before
        state.step += advanced
        bar.advance(advanced)
        if learns:  # update
            state.decisions[name] += 1
            if state.decisions[name] > warmups[name]:
                for _ in range(updates[name]):
                    if (losses := learner.update()) is not None:
                        state.pending[name].add(checked_losses(learner, name, losses) if checked[name] else losses)
        if state.step >= state.next_eval:  # log
            _evaluate(run, state, phase, evaluator, bar)
            state.next_eval += recipe.eval.every


def training_seed(recipe: Recipe, phase: int) -> int:
    """The seed of a phase's first training episode (later ones go on from its generator): `train.seed + phase`."""
    return recipe.train.seed + phase


def _start_episode(env: LayeredEnv, state: LoopState, recipe: Recipe) -> None:
    """Reset the training env: the phase's first episode from its seed, later ones from its generator."""
    if state.episode == 0:
        env.reset(seed=training_seed(recipe, state.phase))
        return
    if state.env_rng is not None:  # the first episode after resuming
        env.base.unwrapped.np_random.bit_generator.state = state.env_rng
        state.env_rng = None
    env.reset()


def _end_episode(run: Training, env: LayeredEnv, state: LoopState) -> None:
    """Log a finished episode; at a boundary past the checkpoint interval, or when asked to stop, checkpoint."""
    if not env.agents:  # the episode ran to its end rather than to the budget
        run.logs.episodes.write({"phase": state.phase, "step": state.step, "return": env.episode_return,
                            "length": env.episode_steps})
    state.episode += 1
    if state.step >= state.next_checkpoint or run.stop.requested:
        _read_back_losses(state, run.learners)
        while state.next_checkpoint <= state.step:
            state.next_checkpoint += checkpoint_interval(run.recipe)
        state.env_rng = dict(env.base.unwrapped.np_random.bit_generator.state)
        run.save(state)
        state.env_rng = None
    if run.stop.requested:
        raise Stopped(run.stop.requested, state.phase, state.step, run.checkpoint.parent.parent)


def _evaluate(run: Training, state: LoopState, phase: Phase, evaluator: Stacks, bar: Progress) -> None:
    """Evaluate the present layers now and log the row, with each learning layer's mean losses since the last."""
    recipe = run.recipe
    _read_back_losses(state, run.learners)
    result = evaluate_run(evaluator, run.learners, recipe.eval.episodes, evaluation_seed(recipe))
    state.curve.append((state.step, result))
    if state.best_index() == len(state.curve) - 1:
        state.best = {name: copy.deepcopy(run.learners[name].state_dict()) for name in phase.learn}
    row = {"phase": state.phase, "learn": "+".join(phase.learn), "step": state.step, **result.row(),
           **mean_losses(state.losses, {name: type(run.learners[name]).loss_names for name in state.losses})}
    run.logs.evaluation(row)
    learned = any(state.losses.values())
    for stats in state.losses.values():
        stats.clear()
    bar.evaluated(state.step, result.return_mean, result.return_std, learned)


def _read_back_losses(state: LoopState, learners: dict[str, Learner]) -> None:
    """Read the losses of each layer's updates since the last read-back off its device in one copy,
    and stop on a non-finite one before it is logged or checkpointed."""
    for name, pending in state.pending.items():
        if not pending:
            continue
        names = type(learners[name]).loss_names
        stats = [{f"{k}_loss": float(losses[k]) if k in losses else None for k in names}
                 for losses, _ in pending.read()]
        _check_finite(np.array([v for s in stats for v in s.values() if v is not None]), "loss", name, state)
        state.losses[name] += stats


def _check_finite(values: np.ndarray, what: str, layer: str, state: LoopState) -> None:
    if not np.all(np.isfinite(values)):
        raise Diverged(f"layer {layer!r} met a non-finite {what} in phase {state.phase} at step {state.step}", layer)


def curve_auc(recipe: Recipe, curve: list[tuple[int, Evaluation]]) -> float | None:
    """The normalised area under a phase's evaluation curve, where the recipe's environment has a return range."""
    return_range = recipe.return_range()
    if return_range is None:
        return None
    return normalised_auc([s for s, _ in curve], [e.return_mean for _, e in curve], return_range)


def phase_row(r: PhaseResult, state: LoopState) -> dict[str, Any]:
    """A phase's results as one flat row of results.json, with its best evaluation's step and return (of
    `state`'s curve)."""
    best_step, best = state.curve[state.best_index()]
    return {
        "phase": r.index, "learn": list(r.phase.learn), "active": list(r.phase.active), "steps": r.steps,
        "auc": r.auc, **r.final.row(), "best_step": best_step, "best_return_mean": best.return_mean,
    }


def fresh_row(label: str, result: Evaluation) -> dict[str, float]:
    """An evaluation on fresh episodes of a phase's `label` (final or best) weights, as its results row's
    `fresh_<label>_<measure>` values."""
    return {f"fresh_{label}_{key}": value for key, value in result.row().items() if key in FRESH_MEASURES}
