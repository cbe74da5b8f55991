"""Decision latency, and the check that an exported stack acts as the library does.

Both run the same real episodes (same seeds) closed loop. The time of a base step is the time
from the observation to the executed action, the environment's own step excluded: for the
library, the agent view's work between two environment calls, as `layered eval` runs it; for an
exported stack, its `step` call.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from layered.agents import make_aec_env
from layered.envs import make_env
from layered.evaluate import run_episode
from layered.learners import Learner
from layered.recipe import Recipe
from layered.runtime import ExportedStack, load_stack

WARMUP_CALLS = 20  # untimed steps first: TorchScript optimises its graph over its first calls


@dataclass(frozen=True)
class Latency:
    """Time per base step over many steps, in microseconds."""

    median_us: float
    p99_us: float
    steps: int

    @classmethod
    def of(cls, seconds: list[float]) -> Latency:
        us = np.asarray(seconds) * 1e6
        return cls(float(np.median(us)), float(np.percentile(us, 99)), len(us))


@dataclass(frozen=True)
class Comparison:
    """The library and an exported stack over the same episodes."""

    episodes: int
    steps: int
    max_difference: float  # largest |library action - exported action| over steps and dimensions
    library: Latency
    exported: Latency

    def row(self) -> dict[str, Any]:
        return asdict(self)


class _StepTimer(gym.Wrapper):
    """Records when each call into the environment (reset or step) starts and ends."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.calls: list[tuple[float, float]] = []

    def reset(self, **kwargs: Any) -> Any:
        start = time.perf_counter()
        out = self.env.reset(**kwargs)
        self.calls.append((start, time.perf_counter()))
        return out

    def step(self, action: Any) -> Any:
        start = time.perf_counter()
        out = self.env.step(action)
        self.calls.append((start, time.perf_counter()))
        return out


def _exported_episode(stack: ExportedStack, env: gym.Env, seed: int) -> tuple[list[np.ndarray], list[float]]:
    obs, _ = env.reset(seed=seed)
    stack.reset()
    actions, seconds = [], []
    while True:
        start = time.perf_counter()
        action = stack.step(obs)
        seconds.append(time.perf_counter() - start)
        actions.append(action)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            return actions, seconds


def _warm_up(stack: ExportedStack, env: gym.Env, seed: int) -> None:
    obs, _ = env.reset(seed=seed)
    stack.reset()
    for _ in range(WARMUP_CALLS):
        stack.step(obs)


def compare(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], exported: Path, episodes: int,
            seed: int, threshold: float | None = None, min_steps: int = 0) -> Comparison:
    """Play `episodes` episodes (seeds seed, seed + 1, ...), and more until `min_steps` base steps,
    with the library and with the stack exported to `exported`; compare their executed actions and
    their time per base step."""
    library = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold, record=True)
    timer = _StepTimer(library.base)
    library.base = timer
    stack = load_stack(exported)
    env = make_env(recipe.env.id)
    _warm_up(stack, env, seed)
    library_seconds: list[float] = []
    exported_seconds: list[float] = []
    difference, steps, k = 0.0, 0, 0
    while k < episodes or steps < min_steps:
        timer.calls.clear()
        run_episode(library, learners, seed + k)
        library_seconds += [start - end for (_, end), (start, _) in zip(timer.calls, timer.calls[1:], strict=False)]
        actions, seconds = _exported_episode(stack, env, seed + k)
        exported_seconds += seconds
        ours = np.asarray([r.action for r in library.trace], np.float64)
        theirs = np.asarray(actions, np.float64)
        if ours.shape != theirs.shape:  # the episodes ended at different steps
            difference = float("inf")
        else:
            difference = max(difference, float(np.max(np.abs(ours - theirs), initial=0.0)))
        steps += len(actions)
        k += 1
    library.close()
    env.close()
    return Comparison(k, steps, difference, Latency.of(library_seconds), Latency.of(exported_seconds))
