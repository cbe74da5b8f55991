"""Deterministic evaluation of K stacks at once, one per seed: the measures `layered.evaluate` takes of
one stack, for each seed, from a batch of rules stepping several environments per seed. A single run
evaluates as a group of one seed does, its episodes side by side."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from layered.env_group import Envs
from layered.env_workers import open_envs
from layered.evaluate import episode_seeds
from layered.learners import Learner
from layered.metrics import EpisodeMeasures, EpisodeMeter, Evaluation, summarise
from layered.rules import Rules
from layered.schema import Recipe
from layered.stack import Stack

GroupPolicy = Callable[[int, np.ndarray], np.ndarray]
"""Layer i's greedy outputs for `n` observations per seed: (i, [K, n, obs]) -> [K, n, size]."""
Stacks = tuple[Stack, Rules, Envs]
"""A phase's stack (for its layers' names, spaces and discounts), its rules over some rows, and their environments."""
EVAL_LANES, EVAL_ROWS = 10, 320
"""At most this many of a seed's evaluation episodes are played side by side, each in an environment of its own,
and at most this many environments in all (a Gymnasium MuJoCo one holds about 1 MB, a dm_control one 13 MB)."""


def eval_lanes(episodes: int, seeds: int) -> int:
    """How many of each seed's `episodes` an evaluation of `seeds` seeds plays side by side: as many as
    `EVAL_LANES` and `EVAL_ROWS` allow, at least one."""
    return max(1, min(episodes, EVAL_LANES, EVAL_ROWS // seeds))


def open_stacks(recipe: Recipe, active: Sequence[str], rows: int, evaluation: bool, gpu: bool = False) -> Stacks:
    """The stack of the `active` layers, its rules over `rows` rows and their environments (for training, or for
    an `evaluation`), stepped as the recipe's `env.workers` says (`gpu`: the learners are on one, for `env.wait`)."""
    env = recipe.env
    envs = open_envs(env.id, rows, env.workers, env.threads, evaluation, env.wait, gpu)
    return stacks_over(recipe, active, envs, evaluation)


def open_group_evaluator(recipe: Recipe, active: Sequence[str], episodes: int, seeds: int,
                         threshold: float | None = None, gpu: bool = False) -> Stacks:
    """A group's evaluator of `episodes` episodes for each of its `seeds` seeds: its stack (at the recipe's evaluation
    thresholds, or `threshold`) over `eval_lanes` rows per seed, stepped as the recipe's `env.workers` says (`gpu`:
    the learners are on one)."""
    env = recipe.env
    envs = open_envs(env.id, seeds * eval_lanes(episodes, seeds), env.workers, env.threads, True, env.wait, gpu)
    return stacks_over(recipe, active, envs, evaluation=True, threshold=threshold)


def stacks_over(recipe: Recipe, active: Sequence[str], envs: Envs, evaluation: bool,
                threshold: float | None = None) -> Stacks:
    """The stack of the `active` layers (at the recipe's evaluation thresholds, or `threshold`) and its rules over
    the rows of `envs`: a threshold sweep's stacks, one per threshold, over the same environments."""
    stack = Stack(recipe, envs.observation_space, envs.action_space, active=list(active), evaluation=evaluation,
                  threshold=threshold)
    rules = Rules([layer.rules for layer in stack.layers], stack.active, stack.low, stack.high, len(envs.obs))
    return stack, rules, envs


def open_run_envs(recipe: Recipe, episodes: int) -> Envs:
    """A single run's evaluation environments for `episodes` episodes: the rows of a group of one seed, stepped in
    this process (as the run's own environment is, so that environments a plugin registers step there too)."""
    return open_envs(recipe.env.id, eval_lanes(episodes, 1), 0, recipe.env.threads, True)


def open_run_evaluator(recipe: Recipe, active: Sequence[str], episodes: int, threshold: float | None = None) -> Stacks:
    """A single run's evaluator of `episodes` episodes: its stack (at the recipe's evaluation thresholds, or
    `threshold`) over `open_run_envs`."""
    return stacks_over(recipe, active, open_run_envs(recipe, episodes), evaluation=True, threshold=threshold)


def close_evaluator(evaluator: Stacks) -> None:
    """Close the environments an evaluator plays its episodes in."""
    evaluator[2].close()


def evaluate_stacks(evaluator: Stacks, learners: Mapping[str, Any], greedy: Callable[[Any, np.ndarray], np.ndarray],
                    episodes: int, seeds: Sequence[int], progress: bool = False) -> list[Evaluation]:
    """`evaluate_group` of the evaluator's rows, each layer acting through its learner in `learners` (a single
    learner or one stacked over the seeds): `greedy(learner, obs)`, its outputs without exploration ([K, n, obs]
    -> [K, n, size]); with `progress`, a bar of the episodes played."""
    stack, rules, envs = evaluator
    names = [layer.name for layer in stack.layers]
    macs = {names[i]: learners[names[i]].act_macs() for i in stack.active}
    with torch_aside(envs):
        return evaluate_group(rules, envs, lambda i, obs: greedy(learners[names[i]], obs), macs, episodes, seeds,
                              progress)


def evaluate_seeds(evaluator: Stacks, learners: Mapping[str, Any], episodes: int, seeds: Sequence[int],
                   progress: bool = False) -> list[Evaluation]:
    """A group's evaluation of each seed's present layers over `episodes` episodes seeded from its seed in `seeds`,
    each layer acting through its learner stacked over the seeds."""
    return evaluate_stacks(evaluator, learners, lambda learner, obs: learner.greedy(obs), episodes, seeds, progress)


def evaluate_run(evaluator: Stacks, learners: Mapping[str, Learner], episodes: int, seed: int,
                 progress: bool = False) -> Evaluation:
    """A single run's evaluation of its present layers over `episodes` episodes seeded from `seed`: what
    `layered.evaluate.evaluate` measures through the agent view, the episodes played side by side."""
    return evaluate_stacks(evaluator, learners, lambda learner, obs: learner.greedy(obs[0])[None], episodes,
                           [seed], progress)[0]


def all_rows(seen: np.ndarray, deciding: np.ndarray) -> np.ndarray:
    """The observations `Rules.decide_all` hands a policy (the deciding rows' only) as one `[rows, obs]` array,
    zeros in the other rows: what a learner stacked over the seeds takes."""
    full = np.zeros((len(deciding), seen.shape[1]), np.float32)
    full[deciding] = seen
    return full


@contextmanager
def torch_aside(envs: Envs) -> Iterator[None]:
    """While `envs` step their rows in several threads (of this process or of workers) with nothing beside them (an
    evaluation): torch on one thread, since its idle workers wait spinning on the cores the rows would step on
    (see docs/performance.md: evaluations of 8 HalfCheetah seeds on 2 cores took half as long again with two)."""
    if envs.stepping < 2:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def evaluate_group(rules: Rules, envs: Envs, policy: GroupPolicy, macs: dict[str, int], episodes: int,
                   seeds: Sequence[int], progress: bool = False) -> list[Evaluation]:
    """Each seed's mean measures over `episodes` episodes seeded as `evaluate` seeds them (`episode_seeds`),
    played side by side: the rules and environments hold `lanes` rows per seed (seed k's lane l is row
    k * lanes + l), lane l playing the seed's episodes l, l + lanes, ...; lanes that have played theirs wait.
    With `progress`, a bar of the episodes played."""
    rows, present = rules.rows, list(rules.active)
    lanes = rows // len(seeds)
    assert lanes * len(seeds) == rows, "an evaluator holds as many rows for every seed"
    starts = [episode_seeds(seed, episodes) for seed in seeds]
    meter = EpisodeMeter(rows, [rules.layers[i].name for i in present], macs, (rules.low, rules.high))
    measured: list[dict[int, EpisodeMeasures]] = [{} for _ in seeds]
    episode = np.arange(rows) % lanes  # the episode each row plays
    live = episode < episodes

    def start(again: np.ndarray) -> None:
        envs.reset(again, [starts[r // lanes][episode[r]] if again[r] else None for r in range(rows)])
        rules.reset(again)

    def act(i: int, seen: np.ndarray, deciding: np.ndarray) -> np.ndarray:
        outputs = policy(i, all_rows(seen, deciding).reshape(len(seeds), lanes, -1))
        return outputs.reshape(rows, -1)[deciding]

    bar = tqdm(total=episodes * len(seeds), desc="evaluating", unit="episode", disable=not progress)
    start(live)
    while live.any():
        decided = rules.decide_all(envs.obs, act)
        composition = rules.compose()
        reward, terminated, truncated = envs.step(composition.action, live)
        rules.tick(live)
        deciding, reached = np.zeros((rows, len(present)), bool), np.zeros((rows, len(present)), bool)
        sizes = np.zeros((rows, len(present)))
        for j, i in enumerate(present):  # and each layer's mean |contribution| where reached (`StepRecord.size`)
            deciding[:, j], reached[:, j] = decided[i], composition.reached[i]
            sizes[:, j] = np.where(composition.reached[i], np.abs(composition.contributions[i]).mean(axis=1), 0.0)
        meter.record(live, composition.action, reward, deciding, sizes, reached)
        ended = live & (terminated | truncated)
        for r in np.flatnonzero(ended).tolist():
            measured[r // lanes][int(episode[r])] = meter.finish(r)
            bar.update()
        episode[ended] += lanes
        again = ended & (episode < episodes)
        if again.any():
            start(again)
        live &= ~ended | again
    bar.close()
    return [summarise([played[j] for j in range(episodes)]) for played in measured]
