"""K environments of one id, one per seed, stepped and reset together by masks over the rows.

Each row is an environment of its own, made and seeded exactly as a single run makes and seeds its
environment, so a row's episodes are the ones that seed would see alone. `EnvGroup` steps its rows one
after the other in this process; `layered.env_workers` steps the same rows in worker processes, each
row by the same functions (`step_rows`, `reset_rows`), so where the rows are stepped changes no number.

A step is asked for (`step_async`) and then collected (`step_wait`), so that a caller can queue work in
between (a group queues its update): in worker processes the rows step meanwhile; here they step when
collected, after the queued work is launched.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box

from layered.envs import EnvSpaces, make_env, restore_env, snapshot_env

StepResult = tuple[np.ndarray, np.ndarray, np.ndarray]
"""The rewards, terminations and truncations of one step of every row ([K] each; zero and False in the
rows not stepped)."""


class Envs(Protocol):
    """K environments of one id with their latest observations as one `[K, obs]` array, in this process or not."""

    env_id: str
    observation_space: Box
    action_space: Box
    obs: np.ndarray
    last: np.ndarray
    """After a step with `restart`: the observations each row's step ended in (`obs` holds the first of the next
    episode where one ended)."""
    stepping: int
    """Threads that step the rows, besides the caller's (in this process or in workers)."""

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        """Start an episode in each row of the `rows` mask; `seeds[k]` seeds row k's environment (None:
        its generator goes on)."""

    def step_async(self, actions: np.ndarray, rows: np.ndarray, restart: bool = False) -> None:
        """Ask for `actions[k]` ([K, action]) to be executed in each row of the `rows` mask; with `restart`, a row
        whose episode ends starts its next one in the same step, unseeded (as `reset` with None does), so that
        no round trip of its own is needed: the step's observations are in `last`, the next decisions' in `obs`."""

    def step_wait(self) -> StepResult:
        """The asked-for step's results, the observations updated in `obs`."""

    def step(self, actions: np.ndarray, rows: np.ndarray) -> StepResult:
        """`step_async` and `step_wait` at once."""
        self.step_async(actions, rows)
        return self.step_wait()

    def snapshots(self) -> list[dict[str, Any]]:
        """Each row's simulator state, mid-episode or not, as `restore` takes it (for a group's checkpoint)."""

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        """Put every row where `snapshots` found it, `obs` its latest observations."""

    def close(self) -> None:
        """Close every environment (and stop any worker)."""


def step_rows(envs: Sequence[gym.Env], actions: np.ndarray, rows: np.ndarray, obs: np.ndarray,
              result: StepResult, last: np.ndarray | None = None) -> None:
    """Step `envs[k]` with `actions[k]` for each k in the `rows` mask, writing its observation into `obs[k]`
    and its reward and flags into `result`'s row k (the other rows are left as they are). With `last`, the
    observation goes there, and a row whose episode ended is reset unseeded (its generator going on, as
    `reset_rows` resets it without a seed), `obs[k]` its next episode's first observation."""
    reward, terminated, truncated = result
    for k in np.flatnonzero(rows).tolist():
        seen, r, terminated[k], truncated[k], _ = envs[k].step(actions[k].astype(np.float32))
        reward[k] = float(r)
        if last is not None:
            last[k] = seen
            if terminated[k] or truncated[k]:
                seen, _ = envs[k].reset(seed=None)
        obs[k] = seen


def reset_rows(envs: Sequence[gym.Env], rows: np.ndarray, seeds: Sequence[int | None], obs: np.ndarray) -> None:
    """Reset `envs[k]` for each k in the `rows` mask, seeded with `seeds[k]` (its action space too) unless None."""
    for k in np.flatnonzero(rows).tolist():
        obs[k], _ = envs[k].reset(seed=seeds[k])
        if seeds[k] is not None:
            envs[k].action_space.seed(seeds[k])


class RowThreads:
    """A process's rows stepped by `threads` Python threads, each a contiguous slice of them, started at once
    and collected later. MuJoCo's step lets go of Python's lock, so the rows' physics runs in parallel (and
    beside the caller's work, such as an update) while their Python takes turns; each row is stepped by one
    thread, so the numbers are those of the rows stepped one after another. 0 threads: the rows step in the
    calling thread, when the step is collected."""

    def __init__(self, envs: Sequence[gym.Env], threads: int) -> None:
        self.envs = envs
        bounds = np.linspace(0, len(envs), min(threads, len(envs)) + 1).round().astype(int).tolist()
        self._slices = [slice(a, b) for a, b in itertools.pairwise(bounds)] if threads else []
        self._pool = ThreadPoolExecutor(len(self._slices), "layered-rows") if self._slices else None
        self._asked: tuple[np.ndarray, np.ndarray, np.ndarray, StepResult, np.ndarray | None] | None = None
        self._running: list[Future[None]] = []

    def start(self, actions: np.ndarray, rows: np.ndarray, obs: np.ndarray, result: StepResult,
              last: np.ndarray | None = None) -> None:
        """Begin stepping the rows of the `rows` mask as `step_rows` does (with copies of `actions` and `rows`,
        which the caller may change meanwhile), into `obs`, `result` and `last`."""
        assert self._asked is None and not self._running, "a step is under way: wait for it first"
        asked = (actions.copy(), rows.copy(), obs, result, last)
        if self._pool is None:
            self._asked = asked
            return
        self._running = [self._pool.submit(_step_slice, self.envs, part, *asked) for part in self._slices
                         if asked[1][part].any()]

    def wait(self) -> None:
        """Wait until the started step is done; the first error a thread met is raised once all are done."""
        if self._asked is not None:
            (actions, rows, obs, result, last), self._asked = self._asked, None
            step_rows(self.envs, actions, rows, obs, result, last)
        running, self._running = self._running, []
        errors = [error for future in running if (error := future.exception()) is not None]
        if errors:
            raise errors[0]

    def close(self) -> None:
        """Stop the threads (after any step under way)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def _step_slice(envs: Sequence[gym.Env], part: slice, actions: np.ndarray, rows: np.ndarray, obs: np.ndarray,
                result: StepResult, last: np.ndarray | None) -> None:
    """`step_rows` on the rows of `part` alone."""
    parts: StepResult = tuple(array[part] for array in result)  # type: ignore[assignment]
    step_rows(envs[part], actions[part], rows[part], obs[part], parts, None if last is None else last[part])


def spaces(env: gym.Env | EnvSpaces) -> tuple[Box, Box]:
    """An environment's observation and action spaces (of one made, or as `env_spaces` read them), both boxes
    (the recipe checks refuse other spaces)."""
    space, action_space = env.observation_space, env.action_space
    assert isinstance(space, Box) and isinstance(action_space, Box), "the recipe checks refuse other spaces"
    return space, action_space


class EnvGroup(Envs):
    """K environments stepped in this process by `threads` threads (`RowThreads`; `Envs`)."""

    def __init__(self, env_id: str, rows: int, threads: int = 0) -> None:
        self.env_id = env_id
        self.envs = [make_env(env_id) for _ in range(rows)]
        self.observation_space, self.action_space = spaces(self.envs[0])
        self.obs = np.zeros((rows, *(self.observation_space.shape or ())), np.float32)
        self.last = np.zeros_like(self.obs)
        self.stepping = threads
        self._threads = RowThreads(self.envs, threads)
        self._result: StepResult | None = None

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        reset_rows(self.envs, rows, seeds, self.obs)

    def step_async(self, actions: np.ndarray, rows: np.ndarray, restart: bool = False) -> None:
        self._result = (np.zeros(len(self.envs)), np.zeros(len(self.envs), bool), np.zeros(len(self.envs), bool))
        if restart:
            np.copyto(self.last, self.obs, where=~rows[:, None])  # (the rows not stepped end where they were)
        self._threads.start(actions, rows, self.obs, self._result, self.last if restart else None)

    def step_wait(self) -> StepResult:
        assert self._result is not None, "step_wait collects the step step_async asked for"
        result, self._result = self._result, None
        self._threads.wait()
        return result

    def snapshots(self) -> list[dict[str, Any]]:
        return [snapshot_env(self.env_id, env) for env in self.envs]

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        for env, snapshot in zip(self.envs, snapshots, strict=True):
            restore_env(self.env_id, env, snapshot)
        self.obs[:] = obs

    def close(self) -> None:
        self._threads.close()
        for env in self.envs:
            env.close()
