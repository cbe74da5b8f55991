"""Deterministic evaluation of K stacks at once, one per seed: the measures `layered.evaluate` takes of
one stack, for every row of a batch of rules stepping K environments."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from layered.env_group import Envs
from layered.metrics import EpisodeMeasures, Evaluation, StepRecord, measure_episode, summarise
from layered.rules import Rules

GroupPolicy = Callable[[int, np.ndarray], np.ndarray]
"""Layer i's greedy outputs for every row's observation: (i, [K, obs]) -> [K, size]."""


def all_rows(seen: np.ndarray, deciding: np.ndarray) -> np.ndarray:
    """The observations `Rules.decide_all` hands a policy (the deciding rows' only) as one `[K, obs]` array,
    zeros in the other rows: what a learner stacked over the K seeds takes."""
    full = np.zeros((len(deciding), seen.shape[1]), np.float32)
    full[deciding] = seen
    return full


def evaluate_group(rules: Rules, envs: Envs, policy: GroupPolicy, macs: dict[str, int], episodes: int,
                   seeds: Sequence[int]) -> list[Evaluation]:
    """Each row's mean measures over `episodes` episodes, its environment seeded once with `seeds[k]`
    as `evaluate` seeds one; rows that have played theirs wait for the others."""
    rows = rules.rows
    names = [layer.name for layer in rules.layers]
    traces: list[list[StepRecord]] = [[] for _ in range(rows)]
    measured: list[list[EpisodeMeasures]] = [[] for _ in range(rows)]
    live = np.ones(rows, bool)
    envs.reset(live, list(seeds))
    rules.reset()

    def act(i: int, seen: np.ndarray, deciding: np.ndarray) -> np.ndarray:
        return policy(i, all_rows(seen, deciding))[deciding]

    while live.any():
        decided = rules.decide_all(envs.obs, act)
        composition = rules.compose()
        before = envs.obs.copy()
        reward, terminated, truncated = envs.step(composition.action, live)
        rules.tick(live)
        for k in np.flatnonzero(live):
            traces[k].append(StepRecord(
                composition.action[k].copy(), float(reward[k]), tuple(names[i] for i, m in decided.items() if m[k]),
                {names[i]: composition.contributions[i][k].copy() for i in rules.active if composition.reached[i][k]},
                before[k]))
        ended = live & (terminated | truncated)
        for k in np.flatnonzero(ended):
            measured[k].append(measure_episode(traces[k], macs))
            traces[k] = []
        again = ended & np.array([len(m) < episodes for m in measured])
        envs.reset(again, [None] * rows)
        rules.reset(again)
        live &= ~ended | again
    return [summarise(m) for m in measured]
