"""Snapshots of environments mid-episode: a fresh env restored from one steps bit for bit like the original,
across episode ends and unseeded resets, and the snapshot is plain data and arrays, which a group's checkpoint
stores as tensors that `torch.load(weights_only=True)` reads."""

import io
import re
import sys
import tomllib
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import layered.envs as envs
from layered.checkpoint_writer import as_arrays, host_copy
from layered.envs.state import TENSOR_DTYPES, StateError, encode_data

RECIPES = Path(__file__).parent.parent / "recipes"

# Every env id of the shipped recipes, the sparse mazes beside their dense ones, and Ant, whose reward reads the
# body positions that its last step left (those before the last substep) before it steps.
ENV_IDS = ["Pendulum-v1", "MountainCarContinuous-v0", "InvertedPendulum-v5", "InvertedDoublePendulum-v5",
           "Hopper-v5", "Walker2d-v5", "Ant-v5", "dmc:cartpole-balance", "dmc:cartpole-swingup", "dmc:cheetah-run",
           "dmc:finger-spin", "dmc:pendulum-swingup", "dmc:reacher-easy", "dmc:walker-walk",
           "robotics:PointMaze_UMaze-v3", "robotics:PointMaze_UMazeDense-v3", "robotics:AntMaze_UMaze-v5",
           "robotics:AntMaze_UMazeDense-v5"]
BEFORE_THE_LIMIT = 10  # snapshots are taken this many steps before a time limit, in envs whose episodes reach it
AFTER = 100  # steps compared at a time after a snapshot


def round_trip(state: dict) -> dict:
    """`state` saved as a group's checkpoint saves it and read back as its loader reads it."""
    buffer = io.BytesIO()
    torch.save(host_copy(state), buffer)
    buffer.seek(0)
    return as_arrays(torch.load(buffer, weights_only=True))


def assert_plain(state, where="snapshot"):
    """Only dicts, lists, tuples, str, int, float, bool, None and numpy arrays: no numpy scalars, no pickled
    objects."""
    if isinstance(state, dict):
        for key, value in state.items():
            assert isinstance(key, str), f"{where} has a key {key!r}"
            assert_plain(value, f"{where}.{key}")
    elif isinstance(state, list | tuple):
        for i, item in enumerate(state):
            assert_plain(item, f"{where}[{i}]")
    else:
        assert type(state) in (str, int, float, bool, type(None), np.ndarray), f"{where} is a {type(state)}"


def step_together(group: list[gym.Env], rng: np.random.Generator, steps: int) -> int:
    """Step every env of `group` with the same random actions, resetting without a seed at each episode end;
    assert they all return the same bits. The number of episode ends."""
    space = group[0].action_space
    ends = 0
    for _ in range(steps):
        action = rng.uniform(space.low, space.high).astype(space.dtype)
        first, *others = [env.step(action) for env in group]
        for other in others:
            assert_same(first, other)
        if first[2] or first[3]:
            ends += 1
            first, *others = [env.reset() for env in group]
            for other in others:
                assert_same(first, other)
    return ends


def step_past_an_end(group: list[gym.Env], rng: np.random.Generator) -> None:
    """`step_together` until past an episode end (which every time limit bounds)."""
    while not step_together(group, rng, AFTER):
        pass


def assert_same(mine: tuple, theirs: tuple) -> None:
    """The same bits in two results of `step` or `reset`: observations, rewards, flags and every entry of
    the info (where MuJoCo envs report positions computed before the step)."""
    *values, info = mine
    *their_values, their_info = theirs
    assert info.keys() == their_info.keys()
    for a, b in zip([*values, *info.values()], [*their_values, *their_info.values()], strict=True):
        assert np.array_equal(a, b), (a, b)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_fresh_env_restored_mid_episode_steps_exactly_like_the_original(env_id):
    """A and C start alike and step alike through an episode end; B, fresh, gets A's snapshot (read back as
    a checkpoint is); then A, B and C go on alike past another episode end. C, never snapshotted, shows that
    taking a snapshot leaves A's own future as it was."""
    a, c = envs.make_env(env_id), envs.make_env(env_id)
    assert_same(a.reset(seed=5), c.reset(seed=5))
    rng = np.random.default_rng(0)
    limit = envs.env_info(env_id).episode_steps
    assert step_together([a, c], rng, 2 * limit - BEFORE_THE_LIMIT) >= 1

    snapshot = envs.snapshot_env(env_id, a)
    assert_plain(snapshot)
    state = round_trip(snapshot)
    assert_plain(state)
    b = envs.make_env(env_id)
    envs.restore_env(env_id, b, state)
    step_past_an_end([a, b, c], rng)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "Hopper-v5", "dmc:reacher-easy", "robotics:PointMaze_UMaze-v3"])
def test_an_env_already_used_is_restored_exactly(env_id):
    """B has run episodes of its own (another goal, another target) before it gets A's snapshot."""
    a, b = envs.make_env(env_id), envs.make_env(env_id)
    rng = np.random.default_rng(1)
    a.reset(seed=1)
    step_together([a], rng, envs.env_info(env_id).episode_steps - BEFORE_THE_LIMIT)
    b.reset(seed=2)
    step_together([b], rng, 50)
    envs.restore_env(env_id, b, envs.snapshot_env(env_id, a))
    step_past_an_end([a, b], rng)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "Hopper-v5", "dmc:reacher-easy", "robotics:PointMaze_UMaze-v3"])
def test_the_snapshot_of_a_new_env_makes_a_used_env_new_again(env_id):
    """Before its first reset an env has no generator and no episode: the used env loses its own."""
    new, used = envs.make_env(env_id), envs.make_env(env_id)
    used.reset(seed=2)
    step_together([used], np.random.default_rng(1), 50)
    envs.restore_env(env_id, used, round_trip(envs.snapshot_env(env_id, new)))
    assert used.unwrapped._np_random is None is new.unwrapped._np_random
    assert_same(new.reset(seed=3), used.reset(seed=3))
    step_together([new, used], np.random.default_rng(4), 30)


def test_an_env_with_state_of_unknown_type_cannot_be_snapshotted(remembering_env_id):
    env = envs.make_env(remembering_env_id)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    with pytest.raises(ValueError, match=r"Remembering-v0 cannot be checkpointed mid-episode: .*recent holds a deque"):
        envs.snapshot_env(remembering_env_id, env)


@pytest.mark.parametrize("array", [np.array(["a"]), np.array([1.0], np.longdouble), np.array([None]),
                                   np.array([1.0], ">f8" if sys.byteorder == "little" else "<f8")])
def test_an_array_a_tensor_cannot_hold_cannot_be_snapshotted(array):
    with pytest.raises(StateError, match=re.escape(f"x[0] is an array of {array.dtype}, which a tensor cannot hold")):
        encode_data([array], "x")
    for dtype in TENSOR_DTYPES:  # (the dtypes taken: a tensor holds each)
        torch.from_numpy(encode_data(np.zeros(2, dtype), "x"))


@pytest.mark.parametrize(("snapshotted", "restored", "problem"), [
    ("Pendulum-v1", "MountainCarContinuous-v0", "was a .*PendulumEnv, not a .*Continuous_MountainCarEnv"),
    ("robotics:PointMaze_UMaze-v3", "robotics:PointMaze_Medium-v3", "its MuJoCo model is not the one snapshotted"),
])
def test_a_snapshot_of_another_env_is_refused(snapshotted, restored, problem):
    state = envs.snapshot_env(snapshotted, envs.make_env(snapshotted))
    with pytest.raises(ValueError, match=f"cannot restore a snapshot into {restored}: .*{problem}"):
        envs.restore_env(restored, envs.make_env(restored), state)


def test_every_shipped_recipes_env_is_tested_here():
    written = {tomllib.loads(path.read_text()).get("env", {}).get("id") for path in RECIPES.rglob("*.toml")}
    assert written - {None} <= set(ENV_IDS)
