"""Shared builders: small recipes over real environments."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import time
from collections import defaultdict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

torch.set_num_threads(1)
# The commands the tests start compute on one thread too: the suite runs a test per core (pytest -n auto), and
# a child on every core beside it ran several times slower than on one (a sweep of a group beside two busy
# processes: 64-84 s against 18).
os.environ["OMP_NUM_THREADS"] = "1"

import layered.runs as runs  # noqa: E402
from layered.checkpoint import load_checkpoint  # noqa: E402
import layered.trainer as trainer  # noqa: E402
from layered.group import Group  # noqa: E402
from layered import Recipe, load_recipe  # noqa: E402


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--plugin", action="append", default=[], metavar="FILE",
                     help="a plugin (file or module) whose entries tests/test_registries.py checks too")


def pytest_configure(config: pytest.Config) -> None:
    from layered.plugins import load_plugin

    for spec in config.getoption("--plugin"):  # (before collection: the registry tests are parametrised over them)
        load_plugin(spec)


def stack_recipe(periods: list[int], kinds: list[str] | str = "residual-clip", env: str = "Pendulum-v1",
                 **extra: Any) -> Recipe:
    """A recipe whose layers l0 (slowest) .. lN-1 have `periods`; each sees obs and every slower layer."""
    kinds = [kinds] * len(periods) if isinstance(kinds, str) else kinds
    layers = [
        {"name": f"l{k}", "period": p, "sees": ["obs", *[f"l{j}" for j in range(k)]],
         **({"combine": kinds[k]} if k < len(periods) - 1 else {})}
        for k, p in enumerate(periods)
    ]
    return load_recipe({"env": {"id": env}, "layers": layers, **extra})


@pytest.fixture(autouse=True)
def registries_as_shipped():
    """Each test starts from the shipped registries: a plugin a test loads (and its module) is gone after it,
    so that no test sees another's learners, combiners, orders or families (the recipe reference lists them)."""
    import sys

    from layered.combiners import COMBINERS
    from layered.envs import FAMILIES
    from layered.learners import LEARNERS
    from layered.orders import ORDERS

    registries = (COMBINERS, FAMILIES, LEARNERS, ORDERS)
    before = [dict(registry._entries) for registry in registries]
    modules = set(sys.modules)
    yield
    for registry, entries in zip(registries, before, strict=True):
        registry._entries = entries
    for name in set(sys.modules) - modules:
        if name.startswith("layered_plugin_"):
            del sys.modules[name]


@pytest.fixture
def tiny() -> list[str]:
    """Overrides that make training a few hundred steps cheap."""
    return ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
            "eval.every=100", "eval.episodes=1", "eval.fresh_episodes=2"]


def layered_here(*args: object) -> subprocess.CompletedProcess:
    """`layered ARGS` run in this process, its exit code and what it printed as a child process gives them:
    for a command that refuses its input, without a child's seconds of loading torch."""
    from layered.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:  # a usage error, from argparse
            code = int(e.code or 0)
    return subprocess.CompletedProcess(["layered", *map(str, args)], code, out.getvalue(), err.getvalue())


def assert_same_run(a: Path, b: Path) -> None:
    """Byte-identical logs, results and layer checkpoints (their tensors compared too, to say which differs)."""
    for name in ("metrics.csv", "episodes.csv", "results.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    layers = sorted(p.name for p in (a / "checkpoints").glob("*.pt") if not p.name.startswith("run"))
    assert layers == sorted(p.name for p in (b / "checkpoints").glob("*.pt") if not p.name.startswith("run"))
    for name in layers:
        layer = name.split(".")[0]
        x, y = (load_checkpoint(d / "checkpoints" / name, layer) for d in (a, b))
        assert_same_state(x, y, name)
        assert (a / "checkpoints" / name).read_bytes() == (b / "checkpoints" / name).read_bytes(), name


def assert_same_state(x, y, where):
    if isinstance(x, dict):
        assert x.keys() == y.keys(), where
        for key in x:
            assert_same_state(x[key], y[key], f"{where}.{key}")
    elif isinstance(x, torch.Tensor):
        assert torch.equal(x, y), where
    else:
        assert x == y, where


def train_until_stopped(monkeypatch, recipe, out: Path, episodes: int, **kwargs) -> None:
    """Train until the loop is asked to stop at the `episodes`-th episode end, as SIGINT would ask."""
    from layered.interrupt import Stopped

    stop_at_episode_end(monkeypatch, episodes)
    with pytest.raises(Stopped):
        runs.train(recipe, out, **kwargs)
    monkeypatch.undo()


def kill_when(proc: subprocess.Popen, ready: Callable[[], bool], timeout: float = 30.0) -> bool:
    """SIGKILL `proc` as soon as `ready()` holds (or at `timeout`); False if it finished first."""
    deadline = time.monotonic() + timeout
    while proc.poll() is None:
        if ready() or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            return True
        time.sleep(0.0005)
    return False


def _written_at(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None


def between_checkpoints(checkpoint: Path, interval: float, rng) -> Callable[[], bool]:
    """A random moment within `interval` seconds after `checkpoint` is next written: a kill there lands between
    two checkpoints after the process has saved progress of its own, so a run outlasts a given number of kills
    however fast the machine (wall-clock moments alone let a fast machine finish first)."""
    before, delay, seen = _written_at(checkpoint), rng.uniform(0.0, interval), None

    def ready() -> bool:
        nonlocal seen
        if seen is None and _written_at(checkpoint) != before:
            seen = time.monotonic()
        return seen is not None and time.monotonic() - seen >= delay

    return ready


def play_through_agent_view(env, next_output: Callable[[str], Any]) -> dict[str, list]:
    """Step an agent view (reset) episode after episode, each due layer given `next_output(name)`, until that is
    None; the transitions each layer was handed, in order."""
    handed: dict[str, list] = defaultdict(list)
    while True:
        for name in env.agent_iter():
            _, _, terminated, truncated, info = env.last()
            if "transition" in info:
                handed[name].append(info["transition"])
            if terminated or truncated:
                env.step(None)
                continue
            if (output := next_output(name)) is None:
                return handed
            env.step(output)
        env.reset()


def stop_at_episode_end(monkeypatch, k: int) -> None:
    """Ask the loop to stop at the k-th episode end, as SIGINT would."""
    original, calls = trainer._end_episode, []

    def end_episode(run, env, state):
        calls.append(1)
        if len(calls) == k:
            run.stop.requested = "SIGINT"
        original(run, env, state)

    monkeypatch.setattr(trainer, "_end_episode", end_episode)


def stop_at(monkeypatch, moments):
    """Ask the group to stop (as SIGINT would) after step `step` of phase `phase`, for each (phase, step)."""
    original, left = Group._due, list(moments)

    def due(self, phase, loop, *args):
        if left and (self.seeds[0].state.phase, loop.step) == left[0]:
            left.pop(0)
            self.stop.requested = "SIGINT"
        original(self, phase, loop, *args)

    monkeypatch.setattr(Group, "_due", due)


class RememberingEnv(gym.Env):
    """A toy env that keeps its recent actions in a deque, a type snapshots have no capture for."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, render_mode: str | None = None) -> None:
        self.render_mode = render_mode
        self.recent: deque[float] = deque(maxlen=3)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.recent.clear()
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.recent.append(float(action[0]))
        return np.array([np.mean(self.recent)], np.float32), 0.0, False, False, {}


@pytest.fixture
def remembering_env_id():
    gym.register("Remembering-v0", entry_point=RememberingEnv, max_episode_steps=10)
    yield "Remembering-v0"
    del gym.registry["Remembering-v0"]
