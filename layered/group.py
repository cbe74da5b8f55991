"""Training K seeds of one recipe as one computation: `layered train RECIPE --seeds 0-4`.

Every base step, the K stacks step together: one `Rules` over K rows decides for every seed at once
(layers due at different steps after a reset, a gate committing in some seeds: masks over the rows),
each layer's learners of the K seeds act as one stacked network (`TD3Group`, or a `ChoiceLearnerGroup`
for the gate's and TempoRL's), and each learning layer updates the seeds it decided in with one masked,
batched update, queued while the K environments step (`layered.env_workers` steps them in processes of
their own), after the transitions that the step's decisions complete are stored, beside the step too: an
update draws from the transitions stored before the step's end, so an episode's last transition joins the
next step's minibatches, not its own step's. What the single loop (`layered.trainer`) does per episode
end, evaluation and phase end is done per seed, and each seed writes its own run directory in the
single run's format, so `eval`, `report` and `export` take any one seed. The numbers are a seed's own
but not bit-identical to its single run (the group draws its noise and minibatches from generators of
its own, and batched products sum in another order); the same group run twice writes the same files,
and a group checkpointed at any step and resumed (`layered.group_state`) writes them too.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
import functools
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import torch

from layered.best_journal import BestJournal, best_folder
from layered.checkpoint_writer import CheckpointWriter, writes_beside
from layered.env_group import Envs
from layered.envs import make_env, snapshot_env
from layered.errors import Diverged
from layered.evaluate import evaluation_seed
from layered.group_eval import Stacks, all_rows, close_evaluator, evaluate_seeds, open_group_evaluator, open_stacks
from layered.group_state import (
    GROUP_CHECKPOINT,
    GroupCheckpoint,
    Pending,
    PhaseLoop,
    check_group_directory,
    check_new_group,
    clear_group,
    clear_group_and_seeds,
    group_info,
    group_snapshot,
    has_group_checkpoint,
    load_group,
    save_group,
    seed_dirs,
)
from layered.heap import keep_freed_memory
from layered.interrupt import StopRequest, Stopped
from layered.learner_set import build_learners, keep_start_weights, precisions, save_layer_weights, start_from_weights
from layered.learners import LEARNERS
from layered.learners.choice_group import ChoiceLearnerGroup
from layered.learners.td3 import TD3Config
from layered.learners.td3_group import TD3Group
from layered.metrics import Evaluation
from layered.orders import Phase, phases_of
from layered.pending_losses import PendingLosses
from layered.progress import Progress, count
from layered.recipe import Recipe, RecipeError, load_recipe, resolved
from layered.replay_journal import ReplayJournal, replay_folder, replays_of
from layered.results import mean_losses, write_finished_phases, write_results
from layered.run_logs import RunLogs
from layered.rundir import (
    RunDirError,
    RunInfo,
    check_same_steps,
    no_checkpoint_to_change,
    prepare_run_dir,
    writing,
)
from layered.rules import Rules
from layered.runs import (
    Change,
    changed_from,
    changed_recipe,
    misfit,
    record,
    training_warnings,
    unavailable_settings,
    way_on,
)
from layered.runstate import LoopState
from layered.stack import Stack
from layered.trainer import (
    PhaseResult,
    checkpoint_interval,
    curve_auc,
    fresh_row,
    phase_budget,
    phase_row,
    training_seed,
)


GroupLearner = TD3Group | ChoiceLearnerGroup


def group_class(kind: str) -> type[GroupLearner] | None:
    """The learner that stacks the seeds' learners of `kind` (taking them as a list): the `Group` that the class
    registered as `kind` names as its own, so that a subclass (whose update may differ) inherits none; None where
    there is none."""
    return vars(LEARNERS.get(kind)).get("Group")

Transitions = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                    list[list[tuple[np.ndarray, float, int]]]]
"""A layer's completed transitions as its group learner's `observe` takes them (see `Group._transitions`)."""


@dataclass
class Seed:
    """One seed of a group: its recipe, its run directory and logs, and its loop state."""

    recipe: Recipe
    out: Path
    logs: RunLogs
    state: LoopState = field(default_factory=LoopState)


SEPARATELY = "train its seeds as runs of their own: `layered sweep` without --vectorize"
"""Where a recipe cannot train as a group, what trains its seeds."""


def check_group(recipe: Recipe) -> None:
    """Refuse, naming each key, what keeps a recipe from training as a group."""
    out = []
    for i, layer in enumerate(recipe.layers):
        kind = recipe.learner_config(i).kind
        if group_class(kind) is None:
            out.append((f"layers[{i}].learner.kind", f"layer {layer.name!r} uses the {kind!r} learner, which does "
                        f"not train as a group yet ({SEPARATELY})"))
            continue
        config = recipe.learner_config(i)
        assert isinstance(config, TD3Config), "every stacked learner is a kind of TD3"
        if config.compile == "inductor":
            out.append((f"layers[{i}].learner.compile", "a group's update runs eagerly ('off') or as CUDA graphs "
                        "('cudagraphs'), not compiled by inductor"))
        if config.actor_anchor:
            out.append((f"layers[{i}].learner.actor_anchor", "a group does not train with an actor anchor yet "
                        f"({SEPARATELY})"))
    out += unavailable_settings(recipe)
    if (problem := _checkpoint_problem(recipe.env.id)) is not None:
        out.append(("env.id", f"{problem}; a group checkpoints its environments mid-episode ({SEPARATELY})"))
    if out:
        raise RecipeError(RecipeError.UNNAMED, out)


@functools.cache  # asked by the command line and again by train_group
def _checkpoint_problem(env_id: str) -> str | None:
    """Why an environment of `env_id`, once reset, cannot be snapshotted (None if it can)."""
    env = make_env(env_id)
    try:
        env.reset(seed=0)
        snapshot_env(env_id, env)
    except ValueError as e:
        return str(e)
    finally:
        env.close()
    return None


def train_group(recipes: Sequence[Recipe], outs: Sequence[Path], label: str, max_steps: int | None = None,
                progress: bool = True, plugins: Sequence[str] = (), resume: bool = False,
                changes: Sequence[Change] = (), force: bool = False) -> list[list[dict[str, Any]]]:
    """Train the recipes (one recipe's seeds: they differ in `train.seed` alone) as one group, seed k into
    `outs[k]` (the group's directory's `seed<k>` folders); the results rows of every phase, per seed.

    With `resume`, the group continues from its last checkpoint (one stopped before its first starts over);
    with `changes` too (one per seed), `recipes` are the seeds' own with some settings changed, recorded in
    each seed's run.json at the step the group continues from. Raises Stopped when SIGINT or SIGTERM stopped
    it, after a checkpoint at the step under way. With `force`, the seeds' directories and the group's checkpoint are
    cleared once the recipes, their settings and their start weights have been checked (a directory that holds
    another group or other files is refused, as without).
    """
    check_group(recipes[0])
    directory = outs[0].parent
    numbers = [recipe.train.seed for recipe in recipes]
    if list(outs) != seed_dirs(directory, numbers):
        raise ValueError(f"a group's run directories are its directory's seed<k> folders, not {list(outs)[:2]}...")
    if not resume:  # (before anything is built or written; with `force`, the seeds' runs go once all is checked)
        (check_group_directory if force else check_new_group)(directory, outs)
    for warning in training_warnings(recipes[0], max_steps):
        print(f"layered: warning: {warning}", file=sys.stderr)
    keep_freed_memory()  # a group's update frees and takes back blocks of MBs every step (layered.heap)
    singles = [build_learners(recipe) for recipe in recipes]
    if not resume:
        for recipe, learners in zip(recipes, singles, strict=True):
            start_from_weights(recipe, learners)
    if force:
        clear_group_and_seeds(directory, outs)
    info = RunInfo(label, max_steps, tuple(plugins), tuple(numbers), threads=torch.get_num_threads())
    resolved_recipes = [resolved(recipe) for recipe in recipes]
    with ExitStack() as locks:
        for out in outs:
            locks.enter_context(writing(out))
        before = [changed_from(out, changes[k] if changes else None) for k, out in enumerate(outs)] if resume else []
        saved = load_group(directory, numbers, resolved_recipes, max_steps, before) if resume else None
        if saved is None and changes:
            raise no_checkpoint_to_change(directory, "group")
        if saved is None:
            clear_group(directory)
        else:
            print(f"layered: the group continues from its checkpoint in phase {saved.states[0].phase} at step "
                  f"{saved.loop.step}", file=sys.stderr)
        seeds = [_open_seed(recipe, out, learners, info, resume, saved, k)
                 for k, (recipe, out, learners) in enumerate(zip(recipes, outs, singles, strict=True))]
        stop = StopRequest(until="this step")
        writer = CheckpointWriter(beside=writes_beside(next(iter(singles[0].values())).device))
        group = Group(seeds, stack_learners(recipes, singles), max_steps, progress, directory, resolved_recipes, stop,
                      ReplayJournal(replay_folder(directory / GROUP_CHECKPOINT)),
                      BestJournal(best_folder(directory / GROUP_CHECKPOINT)), writer)
        del singles
        if saved is not None:
            _take_up(group, saved, changes, before)
        with stop.installed():  # (until the results are written: a signal after the last step lets them finish)
            try:
                with writer:  # (the last checkpoint written before results, or a stop, are reported)
                    group.train(saved)
            except Diverged as e:
                way = way_on(directory, recipes[0], e.layer, has_group_checkpoint(directory))
                raise Diverged(f"{e}; {way}", e.layer) from None
            finally:
                for seed in seeds:
                    seed.logs.close()
            for seed in seeds:
                write_results(seed.recipe, seed.state.rows, seed.out, label)
            clear_group(directory)  # every seed's run directory now holds its results
    return [seed.state.rows for seed in seeds]


def _open_seed(recipe: Recipe, out: Path, learners: dict[str, Any], info: RunInfo, resume: bool,
               saved: GroupCheckpoint | None, k: int) -> Seed:
    """Seed k's run directory and logs, new or (from `saved`) as the group's checkpoint left them."""
    if saved is None:  # (with a checkpoint of the group, its seeds' files are kept as they are)
        prepare_run_dir(out, tomli_w.dumps(resolved(recipe)), info, resume, precisions(learners))
    resumed_at = None if saved is None else (saved.states[k].phase, saved.loop.step)
    seed = Seed(recipe, out, RunLogs.open(out, recipe, resumed_at))
    if saved is None:
        keep_start_weights(recipe, learners, out / "checkpoints")
        seed.logs.begin()
    else:
        seed.state = saved.states[k]  # (its logs are cut back to where it stood once the group is restored)
    return seed


def _take_up(group: Group, saved: GroupCheckpoint, changes: Sequence[Change], before: Sequence[str | None]) -> None:
    """Restore `group` from `saved` and cut its seeds' logs back to where they stood; with `changes` (its
    learners built with changed settings), record them in each seed's run.json, or refuse them in one line,
    with nothing written, where the saved networks do not fit them."""
    try:
        group.restore(saved)
    except (RuntimeError, KeyError, ValueError) as e:
        if not changes:
            raise
        raise misfit(group.directory, e) from None
    for seed in group.seeds:
        seed.logs.begin(seed.state.log_sizes)
    if changes:
        for seed, change, digest in zip(group.seeds, changes, before, strict=True):
            record(seed.out, seed.recipe, change, digest, seed.state.phase, saved.loop.step)


def resume_group(directory: Path, max_steps: int | None = None, progress: bool = True,
                 settings: Sequence[str] = ()) -> list[list[dict[str, Any]]]:
    """Continue the stopped group in `directory` from its last checkpoint, with the recipes it was started with
    or with the `key=value` `settings` changed in every seed (what `layered.runs.resume` lets a run change)."""
    info = group_info(directory)
    check_same_steps(directory, info.max_steps, max_steps, "group")
    outs = seed_dirs(directory, info.group)
    for out, seed in zip(outs, info.group, strict=True):
        if (given := load_recipe(out / "recipe.toml").train.seed) != seed:
            raise RunDirError(f"{out / 'recipe.toml'}: train.seed is {given}, but the group trained seed {seed} "
                              "there; put it back to resume the group")
    if not settings:
        recipes = [load_recipe(out / "recipe.toml") for out in outs]
        return train_group(recipes, outs, info.label, info.max_steps, progress, info.plugins, resume=True)
    changed = [changed_recipe(out, settings, where=directory) for out in outs]
    return train_group([recipe for recipe, _ in changed], outs, info.label, info.max_steps, progress, info.plugins,
                       resume=True, changes=[change for _, change in changed])


def seed_weights(recipe: Recipe, states: Mapping[str, dict[str, Any]], row: int,
                 rows: int) -> dict[str, dict[str, Any]]:
    """Seed row `row`'s weights (single learners' `state_dict`s) in layers' learner states `states` of a group of
    `rows` seeds of `recipe`, as its checkpoint holds them (what `resume_state` returned)."""
    singles = build_learners(recipe, device="cpu")
    groups = stack_learners([recipe] * rows, [singles] * rows)  # (the seeds' own starting weights do not matter)
    for name, state in states.items():
        groups[name].load_resume_state(state)
    return {name: groups[name].seed_state_dict(row) for name in states}


def stack_learners(recipes: Sequence[Recipe], singles: Sequence[dict[str, Any]]) -> dict[str, GroupLearner]:
    """Each layer's learners of every seed as one group, its generators seeded by the layer and the seeds."""
    seeds = [recipe.train.seed for recipe in recipes]
    stacked = {}
    for i, name in enumerate(recipes[0].layer_names()):
        group = group_class(recipes[0].learner_config(i).kind)
        assert group is not None, "check_group refuses a learner that no group stacks"
        stacked[name] = group([learners[name] for learners in singles],
                              seed=int(np.random.SeedSequence([i, *seeds]).generate_state(1)[0]))
    return stacked


class Group:
    """K seeds of a recipe training together, phase by phase, checkpointing every `checkpoint_every` steps."""

    def __init__(self, seeds: list[Seed], learners: dict[str, GroupLearner], max_steps: int | None, progress: bool,
                 directory: Path, recipes: list[dict[str, Any]], stop: StopRequest, journal: ReplayJournal,
                 best: BestJournal, writer: CheckpointWriter) -> None:
        self.seeds, self.learners, self.max_steps, self.progress = seeds, learners, max_steps, progress
        self.directory, self.recipes, self.stop, self.journal, self.best = directory, recipes, stop, journal, best
        self.writer = writer
        self.recipe = seeds[0].recipe
        self.rows = len(seeds)
        self.names = self.recipe.layer_names()
        self.loss_names = {name: type(learner).loss_names for name, learner in learners.items()}

    def restore(self, saved: GroupCheckpoint) -> None:
        """Take up the learners, replay, best weights and generator of `saved` (its loops, `train` takes up)."""
        for name, learner in self.learners.items():
            learner.load_resume_state(saved.learners[name])
        self.journal.restore(saved.replays, replays_of(self.learners))
        self.best.load(saved.best, [seed.state for seed in self.seeds])
        torch.set_rng_state(saved.torch_rng)

    def train(self, saved: GroupCheckpoint | None = None) -> None:
        """Every phase of the training order (from `saved`'s, where it stands, once `restore`d from it), each
        seed's results row recorded at its end."""
        start = -1 if saved is None else saved.states[0].phase  # (the states go on to later phases)
        phases = phases_of(self.recipe)
        for seed in self.seeds:
            if seed.state.rows:  # (resumed: written again for a run whose file is missing, from before it was kept)
                write_finished_phases(seed.state.rows, seed.out)
        for p, phase in enumerate(phases):
            if p < start:
                continue  # its results rows are in the seeds' states
            if p > start:
                for seed in self.seeds:
                    seed.state.start_phase(p, phase.learn, self.recipe.eval.every, checkpoint_interval(self.recipe))
            resumed = saved if p == start else None
            results = self.run_phase(phase, phase_budget(self.recipe, phase, self.max_steps), resumed)
            if p == len(phases) - 1:
                self.stop.finishing()
            rows = self._finish_phase(phase, results)
            for seed, row in zip(self.seeds, rows, strict=True):
                seed.state.finish_phase(row)
                write_finished_phases(seed.state.rows, seed.out)

    @property
    def _gpu(self) -> bool:
        """Whether the learners are on a GPU (for the environments' `env.wait`)."""
        return next(iter(self.learners.values())).device.type == "cuda"

    def _evaluator(self, phase: Phase, episodes: int) -> Stacks:
        """The stacks that play `episodes` evaluation episodes per seed, as many side by side as `eval_lanes` says."""
        return open_group_evaluator(self.recipe, phase.active, episodes, self.rows, gpu=self._gpu)

    def run_phase(self, phase: Phase, budget: int, saved: GroupCheckpoint | None = None) -> list[PhaseResult]:
        """Train `phase.learn` for `budget` base steps in every seed, the other present layers frozen, from
        the start or from where `saved` stands."""
        stack, rules, envs = open_stacks(self.recipe, phase.active, self.rows, evaluation=False, gpu=self._gpu)
        evaluator = self._evaluator(phase, self.recipe.eval.episodes)
        p = self.seeds[0].state.phase
        learn = [self.names.index(name) for name in phase.learn]
        warmups = {i: self.recipe.warmup(self.names[i]) for i in learn}
        loop = PhaseLoop(0, {i: Pending.empty(self.rows, stack.observation_spaces[i].shape[0],
                                              stack.layers[i].rules.size, stack.layers[i].layout.repeats)
                             for i in learn},
                         np.zeros(self.rows), np.zeros(self.rows, np.int64))
        decisions = {i: np.zeros(self.rows, np.int64) for i in learn}
        if saved is not None:
            loop = saved.loop
            for i in learn:
                decisions[i][:] = [seed.state.decisions[self.names[i]] for seed in self.seeds]
        pending = loop.pending
        queued: list[tuple[int, Transitions]] = []  # the decisions' transitions, stored while the environments step
        losses = {self.names[i]: PendingLosses() for i in learn}
        every = np.ones(self.rows, bool)
        label = f"phase {p}: {'+'.join(phase.learn)} ({count(self.rows, 'seed')})"
        bar = Progress(label, budget, loop.step, self.progress, self.rows, len(phases_of(self.recipe)) - 1 - p)

        def act(i: int, seen: np.ndarray, deciding: np.ndarray) -> np.ndarray:
            full = all_rows(seen, deciding)
            group = self.learners[self.names[i]]
            if i not in pending:
                return group.act(full, explore=False)[deciding]
            mine = pending[i]
            if (transitions := self._transitions(i, mine, deciding & mine.open, full, np.zeros(self.rows, bool),
                                                 stack)) is not None:
                queued.append((i, transitions))
            explored = group.act(full, explore=True)
            outputs = np.where((decisions[i] < warmups[i])[:, None], group.random_action(), explored)
            mine.decide(deciding, seen)
            decisions[i] += deciding
            return outputs[deciding]

        try:
            self._begin(phase, saved, rules, envs, evaluator, losses, bar)
            while loop.step < budget:
                decided = rules.decide_all(envs.obs, act)
                for i, rows in decided.items():
                    if i in pending:
                        pending[i].output[rows] = rules.decided[i][rows]
                        _check_finite(rules.decided[i][rows], "action", self.names[i], p, loop.step)
                composition = rules.compose()
                envs.step_async(composition.action, every, restart=True)  # (an episode that ends starts again)
                for i, transitions in queued:  # stored, then updated on, while the environments step (on a GPU, or
                    self.learners[self.names[i]].observe(*transitions)  # with env.workers): the host waits there
                queued.clear()
                for i in learn:
                    self._update(self.names[i], decided[i] & (decisions[i] > warmups[i]), losses)
                reward, terminated, truncated = envs.step_wait()
                _check_finite(envs.last, "observation", None, p, loop.step)
                shares = rules.layer_rewards(reward, composition)
                rules.tick()
                ended = terminated | truncated
                for i, mine in pending.items():
                    mine.accrue(shares[i])
                _end_periods(pending, ended, rules, envs.last, stack)
                loop.returns += reward
                loop.lengths += 1
                loop.step += 1
                bar.advance(1)
                if ended.any():
                    for i, mine in pending.items():
                        self._store(i, mine, ended & mine.open, rules.observation(i, envs.last), terminated, stack)
                        mine.open[ended] = False
                    self._log_episodes(ended, p, loop)
                    rules.reset(ended)  # (the environments of those rows started their next episodes already)
                self._due(phase, loop, {self.names[i]: d for i, d in decisions.items()}, losses, rules, envs,
                          evaluator, bar)
            if self.seeds[0].state.curve[-1][0] != loop.step:
                self._evaluate(phase, evaluator, losses, loop.step, bar)
        finally:
            bar.close()
            envs.close()
            close_evaluator(evaluator)
        return [PhaseResult(p, phase, loop.step, seed.state.curve[-1][1], curve_auc(self.recipe, seed.state.curve))
                for seed in self.seeds]

    def _begin(self, phase: Phase, saved: GroupCheckpoint | None, rules: Rules, envs: Envs,
               evaluator: Stacks, losses: dict[str, PendingLosses], bar: Progress) -> None:
        """Start the phase (its evaluation at step 0 and every row's first, seeded episode), or put the
        rules' rows and the environments where `saved` found them."""
        if saved is not None:
            envs.restore(saved.envs, saved.obs)
            rules.load_state_dict(saved.rules)
            return
        self._evaluate(phase, evaluator, losses, 0, bar)
        p = self.seeds[0].state.phase
        envs.reset(np.ones(self.rows, bool), [training_seed(seed.recipe, p) for seed in self.seeds])
        rules.reset()

    def _due(self, phase: Phase, loop: PhaseLoop, decisions: dict[str, np.ndarray],
             losses: dict[str, PendingLosses], rules: Rules, envs: Envs,
             evaluator: Stacks, bar: Progress) -> None:
        """What is due after a step: an evaluation, a checkpoint, and the stop a signal asked for."""
        state = self.seeds[0].state
        if loop.step >= state.next_eval:
            self._evaluate(phase, evaluator, losses, loop.step, bar)
            for seed in self.seeds:
                seed.state.next_eval += self.recipe.eval.every
        if loop.step >= state.next_checkpoint or self.stop.requested:
            self._checkpoint(loop, decisions, losses, rules, envs)
        if self.stop.requested:
            self.writer.wait()  # on disk before the stop says so (a write that failed is the error instead)
            raise Stopped(self.stop.requested, state.phase, loop.step, self.directory)

    def _checkpoint(self, loop: PhaseLoop, decisions: dict[str, np.ndarray], losses: dict[str, PendingLosses],
                    rules: Rules, envs: Envs) -> None:
        """Save where the group stands, at any step: each seed's loop state (its losses read back first and
        its logs' sizes), the phase's open transitions, the rules' rows, the environments and the learners;
        where the writer is beside training, copied here and written while the group goes on
        (`layered.checkpoint_writer`)."""
        self.writer.wait()  # the checkpoint before is on disk, what it replaced removed: this one records from there
        _read_back(losses, self.loss_names, self.seeds, loop.step)
        interval = checkpoint_interval(self.recipe)
        for k, seed in enumerate(self.seeds):
            state = seed.state
            state.step = loop.step
            state.decisions = {name: int(d[k]) for name, d in decisions.items()}
            while state.next_checkpoint <= loop.step:
                state.next_checkpoint += interval
            state.log_sizes = seed.logs.sizes()
        numbers, states = [seed.recipe.train.seed for seed in self.seeds], [seed.state for seed in self.seeds]
        replays = self.journal.record(replays_of(self.learners))  # (the rows stored since the last checkpoint)
        best = self.best.record(numbers, states)  # (the best weights of seeds whose best changed since)
        snapshot = group_snapshot(numbers, self.recipes, self.max_steps,
                                  GroupCheckpoint(states, loop, rules.state_dict(), envs.snapshots(), envs.obs,
                                                  {name: g.resume_state() for name, g in self.learners.items()},
                                                  torch.get_rng_state(), replays, best), self.writer.beside)

        def write() -> None:
            save_group(self.directory, snapshot)
            self.journal.prune()
            self.best.prune()

        self.writer.start(write)

    def _log_episodes(self, ended: np.ndarray, phase: int, loop: PhaseLoop) -> None:
        """Log the episodes that ended in the `ended` rows, and start their counts again."""
        for k in np.flatnonzero(ended):
            row = {"phase": phase, "step": loop.step, "return": loop.returns[k], "length": int(loop.lengths[k])}
            self.seeds[k].logs.episodes.write(row)
            self.seeds[k].state.episode += 1
        loop.returns[ended], loop.lengths[ended] = 0.0, 0

    def _update(self, name: str, ready: np.ndarray, losses: dict[str, PendingLosses]) -> None:
        """Layer `name`'s updates (`updates` per decision) in the seeds of the `ready` mask."""
        if not ready.any():
            return
        for _ in range(self.recipe.layers[self.names.index(name)].updates):
            if (result := self.learners[name].update(ready)) is not None:
                losses[name].add({n: values for n, (values, _) in result.items()},
                                 {n: took for n, (_, took) in result.items()})

    def _store(self, i: int, mine: Pending, rows: np.ndarray, next_seen: np.ndarray, terminated: np.ndarray,
               stack: Stack) -> None:
        """Store layer i's completed transitions in the `rows`, now that it sees `next_seen`."""
        if (transitions := self._transitions(i, mine, rows, next_seen, terminated, stack)) is not None:
            self.learners[self.names[i]].observe(*transitions)

    @staticmethod
    def _transitions(i: int, mine: Pending, rows: np.ndarray, next_seen: np.ndarray, terminated: np.ndarray,
                     stack: Stack) -> Transitions | None:
        """Layer i's completed transitions in the `rows`, now that it sees `next_seen`, as its learner's `observe`
        takes them, copied out of `mine` (which the layer's next decisions overwrite); None where there are none."""
        if not rows.any():
            return None
        return (mine.seen.copy(), mine.output.copy(), mine.reward.copy(), next_seen, terminated,
                stack.layers[i].discounts(mine.elapsed), rows, list(mine.path))

    def _evaluate(self, phase: Phase, evaluator: Stacks, losses: dict[str, PendingLosses],
                  step: int, bar: Progress) -> None:
        """Evaluate every seed's present layers now and log its row, with its mean losses since the last."""
        results = self._evaluations(evaluator, self.recipe.eval.episodes)
        _read_back(losses, self.loss_names, self.seeds, step)
        learned = any(any(seed.state.losses.values()) for seed in self.seeds)
        for k, (seed, result) in enumerate(zip(self.seeds, results, strict=True)):
            state = seed.state
            state.curve.append((step, result))
            if state.best_index() == len(state.curve) - 1:
                state.best = {name: self.learners[name].seed_state_dict(k) for name in phase.learn}
            row = {"phase": state.phase, "learn": "+".join(phase.learn), "step": step, **result.row(),
                   **mean_losses(state.losses, self.loss_names)}
            state.losses = {name: [] for name in phase.learn}
            seed.logs.evaluation(row)
        returns = np.array([r.return_mean for r in results])
        bar.evaluated(step, float(returns.mean()), float(returns.std()), learned)

    def _evaluations(self, evaluator: Stacks, episodes: int, fresh: bool = False) -> list[Evaluation]:
        """Each seed's evaluation of the evaluator's present layers over `episodes` episodes seeded from its
        `evaluation_seed` (`fresh`: its fresh episodes'), as many side by side as the evaluator has lanes."""
        return evaluate_seeds(evaluator, self.learners, episodes, [evaluation_seed(seed.recipe, fresh)
                                                                  for seed in self.seeds])

    def _finish_phase(self, phase: Phase, results: list[PhaseResult]) -> list[dict[str, Any]]:
        """Each seed's phase end as the single loop's: its final and best weights saved, both evaluated on
        fresh episodes, and the learners left holding the ones `train.select` hands on; its results row."""
        rows = []
        for k, (seed, result) in enumerate(zip(self.seeds, results, strict=True)):
            folder = seed.out / "checkpoints"
            for name in phase.learn:
                save_layer_weights(folder, name, self.learners[name].seed_state_dict(k), seed.state.best[name])
            rows.append(phase_row(result, seed.state))
        final = {name: [self.learners[name].seed_state_dict(k) for k in range(self.rows)] for name in phase.learn}
        evaluator = self._evaluator(phase, self.recipe.eval.fresh_episodes) if self.recipe.eval.fresh_episodes else None
        try:
            self._fresh(evaluator, rows, "final")
            for k, seed in enumerate(self.seeds):
                for name in phase.learn:
                    self.learners[name].load_seed_state_dict(k, seed.state.best[name])
            self._fresh(evaluator, rows, "best")
        finally:
            if evaluator is not None:
                close_evaluator(evaluator)
        if self.recipe.train.select == "final":
            for name, states in final.items():
                for k, state in enumerate(states):
                    self.learners[name].load_seed_state_dict(k, state)
        return rows

    def _fresh(self, evaluator: Stacks | None, rows: list[dict[str, Any]], label: str) -> None:
        """Add each seed's `fresh_<label>_<measure>` evaluation on `eval.fresh_episodes` episodes to its row (none
        without an evaluator: `eval.fresh_episodes` is 0)."""
        if evaluator is None:
            return
        results = self._evaluations(evaluator, self.recipe.eval.fresh_episodes, fresh=True)
        for row, result in zip(rows, results, strict=True):
            row |= fresh_row(label, result)


def _end_periods(pending: dict[int, Pending], ended: np.ndarray, rules: Rules, obs: np.ndarray, stack: Stack) -> None:
    """Where a repeating learning layer's period ends at this step (or the episode does), its open decisions'
    paths grow, as `Stack.accrue` books them for one stack."""
    for i, mine in pending.items():
        if not mine.repeats:
            continue
        ends = mine.open & ((rules.t % stack.layers[i].period == 0) | ended)
        if ends.any():
            mine.end_periods(ends, rules.observation(i, obs), stack.layers[i].discount_units)


def _read_back(losses: dict[str, PendingLosses], loss_names: Mapping[str, Sequence[str]], seeds: Sequence[Seed],
               step: int) -> None:
    """Add the losses of each layer's updates since the last read-back to each seed's loop state (each
    update a seed took part in, as the single loop's `UpdateStats`), read off the device in one copy per
    layer; a non-finite one stops the group."""
    for name, pending in losses.items():
        read = pending.read()
        if not read:
            continue
        took = np.stack([masks["critic"] for _, masks in read])  # [updates, K]: the seeds each update stepped
        none, zeros = np.zeros_like(took[0]), np.zeros(took.shape[1], np.float32)  # (a loss an update lacks)
        columns = {}  # per loss: [updates, K] values, and whether the update computed them for the seed
        for n in loss_names[name]:
            computed = np.stack([masks.get(n, none) for _, masks in read]) & took
            values = np.stack([update.get(n, zeros) for update, _ in read])
            _check_finite(values[computed], "loss", name, seeds[0].state.phase, step)
            columns[f"{n}_loss"] = (values, computed)
        for k, seed in enumerate(seeds):
            updates = np.flatnonzero(took[:, k])
            per_loss = [[value if kept else None for value, kept in zip(values[updates, k].tolist(),
                                                                        computed[updates, k].tolist(), strict=True)]
                        for values, computed in columns.values()]
            seed.state.losses[name] += [dict(zip(columns, stats, strict=True)) for stats in zip(*per_loss, strict=True)]


def _check_finite(values: np.ndarray, what: str, layer: str | None, phase: int, step: int) -> None:
    """Stop the group (`Diverged`, naming `layer`, None for the environment) at a non-finite value."""
    if not np.all(np.isfinite(values)):
        who = "the environment" if layer is None else f"layer {layer!r}"
        raise Diverged(f"{who} met a non-finite {what} in phase {phase} at step {step} of a group", layer)


def group_recipes(path: str | Path, seeds: Sequence[int], overrides: Sequence[str]) -> list[Recipe]:
    """The recipe at `path` with `overrides`, once per seed."""
    return [load_recipe(path, [*overrides, f"train.seed={seed}"]) for seed in seeds]
