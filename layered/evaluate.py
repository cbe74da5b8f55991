"""Deterministic evaluation of a stack: every present layer acts without exploration noise."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from layered.agents import LayeredEnv, make_aec_env
from layered.learners import Learner
from layered.metrics import EpisodeMeasures, Evaluation, StepRecord, measure_episode, summarise
from layered.schema import Recipe


def run_episode(env: LayeredEnv, learners: Mapping[str, Learner], seed: int | None) -> EpisodeMeasures:
    """Play one episode on a recording env and measure it."""
    env.reset(seed=seed)
    for name in env.agent_iter():
        obs, _, terminated, truncated, _ = env.last()
        env.step(None if terminated or truncated else learners[name].act(obs, explore=False))
    macs = {name: learners[name].act_macs() for name in env.possible_agents}
    return measure_episode(env.trace, macs, (env.stack.low, env.stack.high))


def evaluation_seed(recipe: Recipe, fresh: bool = False) -> int:
    """The seed a run's evaluations draw their episodes from (`episode_seeds`): `train.seed + eval.seed_offset`, or
    with `fresh` that of the fresh episodes each phase's final and best weights are measured on at its end."""
    evaluation = recipe.eval
    return recipe.train.seed + (evaluation.fresh_seed_offset if fresh else evaluation.seed_offset)


def episode_seeds(seed: int, episodes: int) -> list[int]:
    """The seeds of an evaluation's episodes, drawn from `seed`: each episode starts where it would whatever was
    played before it (so that episodes can be played side by side, as a group does), and the episodes of
    evaluations seeded differently do not overlap."""
    return np.random.SeedSequence(seed).generate_state(episodes).tolist()


def evaluate(
    env: LayeredEnv, learners: Mapping[str, Learner], episodes: int, seed: int, progress: bool = False
) -> Evaluation:
    """Mean measures over `episodes` episodes, seeded `episode_seeds(seed, episodes)`: each call, the same starts.
    One after another through the agent view: the reference that side-by-side evaluations (`layered.group_eval`,
    which the command line and training use) are tested against."""
    assert env.keep_trace, "evaluation needs an env made with keep_trace=True"
    seeds = tqdm(episode_seeds(seed, episodes), desc="evaluating", unit="episode", disable=not progress)
    return summarise([run_episode(env, learners, episode_seed) for episode_seed in seeds])


def distinct_states(points: Sequence[np.ndarray], count: int) -> list[int]:
    """Indices of up to `count` points that differ most: farthest-point sampling in standardised
    coordinates, from the first point; returned in order of index."""
    if not points:
        return []
    x = np.asarray(points, np.float64)
    x = (x - x.mean(axis=0)) / np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0)
    chosen = [0]
    nearest = np.linalg.norm(x - x[0], axis=1)
    while len(chosen) < min(count, len(x)) and nearest.max() > 0:
        chosen.append(int(nearest.argmax()))
        nearest = np.minimum(nearest, np.linalg.norm(x - x[chosen[-1]], axis=1))
    return sorted(chosen)


Shot = tuple[int, int, np.ndarray, StepRecord]  # an episode, its base step, the state rendered before it, what acted


@dataclass
class _Shots:
    """A watcher that keeps the frames of chosen base steps of one episode with what was executed there."""

    episode: int
    steps: set[int]
    taken: list[Shot] = field(default_factory=list)

    def wants(self, step: int) -> bool:
        return step in self.steps

    def __call__(self, step: int, frame: np.ndarray, record: StepRecord) -> None:
        self.taken.append((self.episode, step, frame, record))


def states_where_layer_acts(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], layer: str, seed: int,
                            episodes: int, threshold: float | None = None, count: int = 8
                            ) -> tuple[int, int, list[Shot]]:
    """At how many of the base steps of `layered eval`'s `episodes` episodes (seeded `episode_seeds(seed, episodes)`)
    `layer` changed the action, of how many, and rendered frames of up to `count` of those states whose observations
    differ most. Each episode holding a chosen state is played again to render it (it is deterministic given its
    seed)."""
    env = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold, keep_trace=True,
                       render_mode="rgb_array")
    seeds = episode_seeds(seed, episodes)
    acting: list[tuple[int, int]] = []  # (episode, step)
    observations, steps = [], 0
    for episode, episode_seed in enumerate(seeds):
        run_episode(env, learners, episode_seed)
        steps += len(env.trace)
        acted = [t for t, step in enumerate(env.trace) if layer in step.acted]
        acting += [(episode, t) for t in acted]
        observations += [env.trace[t].obs for t in acted]
    chosen = [acting[k] for k in distinct_states(observations, count)]
    taken: list[Shot] = []
    for episode in sorted({episode for episode, _ in chosen}):
        env.watcher = shots = _Shots(episode, {t for e, t in chosen if e == episode})
        run_episode(env, learners, seeds[episode])
        taken += shots.taken
    env.close()
    return len(acting), steps, taken
