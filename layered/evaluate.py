"""Deterministic evaluation of a stack: every present layer acts without exploration noise."""

from __future__ import annotations

from collections.abc import Mapping

from tqdm import tqdm

from layered.agents import LayeredEnv
from layered.learners import Learner
from layered.metrics import EpisodeMeasures, Evaluation, measure_episode, summarise


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
