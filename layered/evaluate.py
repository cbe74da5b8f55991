"""Deterministic evaluation of a stack: every present layer acts without exploration noise."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from layered.agents import LayeredEnv, make_aec_env
from layered.learners import Learner
from layered.metrics import EpisodeMeasures, Evaluation, measure_episode, summarise
from layered.recipe import Recipe


def run_episode(env: LayeredEnv, learners: Mapping[str, Learner], seed: int | None) -> EpisodeMeasures:
    """Play one episode on a recording env and measure it."""
    env.reset(seed=seed)
    for name in env.agent_iter():
        obs, _, terminated, truncated, _ = env.last()
        env.step(None if terminated or truncated else learners[name].act(obs, explore=False))
    return measure_episode(env.trace, {name: learners[name].act_macs() for name in env.possible_agents})


def evaluate(
    env: LayeredEnv, learners: Mapping[str, Learner], episodes: int, seed: int, progress: bool = False
) -> Evaluation:
    """Mean measures over `episodes` episodes; the env is seeded once, so every call sees the same starts."""
    assert env.record, "evaluation needs an env made with record=True"
    runs = tqdm(range(episodes), desc="evaluating", unit="episode", disable=not progress)
    return summarise([run_episode(env, learners, seed if k == 0 else None) for k in runs])


def threshold_sweep(
    recipe: Recipe, learners: Mapping[str, Learner], active: list[str], thresholds: Sequence[float],
    episodes: int, seed: int,
) -> list[dict[str, Any]]:
    """One evaluation per threshold (fraction of max action): the paper's return and action
    frequency against the threshold."""
    rows = []
    for threshold in tqdm(thresholds, desc="threshold sweep", unit="threshold"):
        env = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold, record=True)
        rows.append({"threshold": threshold, **evaluate(env, learners, episodes, seed).row()})
        env.close()
    return rows


def frames_where_layer_acts(
    recipe: Recipe, learners: Mapping[str, Learner], active: list[str], layer: str, seed: int
) -> list[tuple[int, np.ndarray]]:
    """Rendered states of one evaluation episode at which `layer` changed the action."""
    env = make_aec_env(recipe, active=active, evaluation=True, record=True, render_mode="rgb_array")
    env.capture = layer
    run_episode(env, learners, seed)
    env.close()
    return env.frames
