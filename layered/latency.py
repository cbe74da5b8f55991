"""Decision latency, and the check that an exported stack acts as the library does.

The library plays real episodes closed loop, as `layered eval` does; the exported stack is given
the very observations of each of those episodes, in order, and its actions are compared with the
library's at each step. So the comparison measures the export itself: a closed loop would let the
float32 kernels of another backend (ONNX sums in another order) compound into another trajectory.
Both also play each episode closed loop, and their returns are reported side by side. The time of
a base step is the time from the observation to the executed action, the environment's own step
excluded: for the library, the agent view's work between two environment calls; for an exported
stack, its `step` call.
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
from layered.evaluate import episode_seeds, run_episode
from layered.metrics import StepRecord
from layered.learners import Learner
from layered.schema import Recipe
from layered.runtime import ExportedStack, load_stack

WARMUP_CALLS = 20  # untimed steps first: TorchScript optimises its graph over its first calls
TOLERANCE = 1e-5  # of the action range: float32 kernels that sum in another order differ by about 1e-7 of it


@dataclass(frozen=True)
class Latency:
    """Time per base step over many steps, in microseconds."""

    median_us: float
    p99_us: float
    steps: int

    @classmethod
    def of(cls, seconds: list[float]) -> Latency:
        """The median and 99th percentile of `seconds`, in microseconds, and their count."""
        us = np.asarray(seconds) * 1e6
        return cls(float(np.median(us)), float(np.percentile(us, 99)), len(us))


@dataclass(frozen=True)
class Comparison:
    """The library and an exported stack over the same episodes."""

    episodes: int
    steps: int
    max_difference: float  # largest |library action - exported action| on the library's observations
    tolerance: float  # what float32 kernels summing in another order may differ by
    library_return: float  # mean return of the episodes closed loop
    exported_return: float
    library: Latency
    exported: Latency

    @property
    def matches(self) -> bool:
        """Whether the exported stack executes the library's actions up to float32 rounding."""
        return self.max_difference <= self.tolerance

    def row(self) -> dict[str, Any]:
        return {**asdict(self), "matches": self.matches}


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


def _exported_episode(stack: ExportedStack, env: gym.Env, seed: int) -> float:
    """The return of one episode of the exported stack, closed loop."""
    obs, _ = env.reset(seed=seed)
    stack.reset()
    total, ended = 0.0, False
    while not ended:
        obs, reward, terminated, truncated, _ = env.step(stack.step(obs))
        total, ended = total + float(reward), terminated or truncated
    return total


def _replay(stack: ExportedStack, trace: list[StepRecord]) -> tuple[np.ndarray, list[float]]:
    """The exported stack's actions given the library's observations of one episode, and their times."""
    stack.reset()
    actions, seconds = [], []
    for record in trace:
        start = time.perf_counter()
        actions.append(stack.step(record.obs))
        seconds.append(time.perf_counter() - start)
    return np.asarray(actions, np.float64), seconds


def _warm_up(stack: ExportedStack, env: gym.Env, seed: int) -> None:
    obs, _ = env.reset(seed=seed)
    stack.reset()
    for _ in range(WARMUP_CALLS):
        stack.step(obs)


def compare(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], exported: Path, episodes: int,
            seed: int, threshold: float | None = None, min_steps: int = 0) -> Comparison:
    """Play `episodes` episodes (`layered eval`'s, seeded `episode_seeds(seed, ...)`), and more until `min_steps`
    base steps, with the library; replay each one's observations through the stack exported to `exported` and
    compare the actions; play each closed loop with the exported stack too; time both per base step."""
    library = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold, keep_trace=True)
    timer = _StepTimer(library.base)
    library.base = timer
    stack = load_stack(exported)
    env = make_env(recipe.env.id)
    _warm_up(stack, env, seed)
    library_seconds: list[float] = []
    exported_seconds: list[float] = []
    library_returns, exported_returns = [], []
    difference, steps, k = 0.0, 0, 0
    while k < episodes or steps < min_steps:
        timer.calls.clear()
        episode_seed = episode_seeds(seed, k + 1)[k]  # (a longer draw begins with the shorter one)
        library_returns.append(run_episode(library, learners, episode_seed).ret)
        library_seconds += [start - end for (_, end), (start, _) in zip(timer.calls, timer.calls[1:], strict=False)]
        actions, seconds = _replay(stack, library.trace)
        exported_seconds += seconds
        ours = np.asarray([r.action for r in library.trace], np.float64)
        difference = max(difference, float(np.max(np.abs(ours - actions), initial=0.0)))
        exported_returns.append(_exported_episode(stack, env, episode_seed))
        steps += len(actions)
        k += 1
    library.close()
    env.close()
    tolerance = TOLERANCE * float(np.max(stack.rules.high - stack.rules.low))
    return Comparison(k, steps, difference, tolerance, float(np.mean(library_returns)),
                      float(np.mean(exported_returns)), Latency.of(library_seconds), Latency.of(exported_seconds))

