"""The jointly trained gate's learner for K seeds as one computation: each seed acts, learns its gate and
checkpoints as its own `GateTD3` learner."""

import numpy as np
import pytest
import torch
from gymnasium.spaces import Box

from layered.buffer import Transition
from layered.learners.choice_group import GateTD3Group, TempoRLGroup
from layered.learners.gate_td3 import GateTD3, GateTD3Config
from layered.learners.temporl import TempoRL, TempoRLConfig
from layered.outputs import GateEncoding, OutputLayout

OBS = Box(-1.0, 1.0, (3,), np.float32)
OUT = Box(np.array([-2.0, -1.0], np.float32), np.array([2.0, 1.0], np.float32))  # an action, then the gate
LAYOUT = OutputLayout(1, gate_dims=1, gate=GateEncoding())
CONFIG = GateTD3Config(hidden=(32, 16), batch_size=8, buffer_size=100)


def learners(seeds, config=CONFIG):
    return [GateTD3(OBS, OUT, LAYOUT, config, seed) for seed in seeds]


def transitions(seeds, gate):
    """One made-up transition per seed (seed k's offset by k), its gate output `gate[k]`."""
    obs = np.arange(3, dtype=np.float32)[None] * 0.1 + np.arange(len(seeds), dtype=np.float32)[:, None] * 0.2
    output = np.stack([np.full(len(seeds), 0.5, np.float32), np.asarray(gate, np.float32)], axis=1)
    return obs, output, np.array([1.0, -0.5, 0.25][: len(seeds)]), obs * 0.5, np.zeros(len(seeds), bool), \
        np.full(len(seeds), 0.99)


def test_a_group_acts_as_its_seeds_gate_learners():
    singles = learners([0, 1, 2])
    group = GateTD3Group(singles)
    obs = np.random.default_rng(1).uniform(-1, 1, (3, 3)).astype(np.float32)
    acted = group.act(obs, explore=False)
    for k, single in enumerate(singles):
        assert acted[k] == pytest.approx(single.act(obs[k], explore=False), abs=1e-6)
    assert set(group.random_action()[:, 1]) <= {-1.0, 1.0}
    explored = np.concatenate([group.act(obs, explore=True) for _ in range(50)])
    assert set(explored[:, 1]) == {-1.0, 1.0}  # epsilon-greedy: both choices come up


def test_one_gate_update_of_the_group_is_each_seeds_own():
    """With one stored transition per seed, every minibatch is that transition: the group's gate regression
    then gives each seed the weights its own `ChoiceQ.update` gives (before any target moves)."""
    singles, seeds, gate = learners([0, 1]), [0, 1], [1.0, -1.0]
    group = GateTD3Group(singles)
    obs, output, reward, next_obs, terminated, discount = transitions(seeds, gate)
    group.observe(obs, output, reward, next_obs, terminated, discount)
    group.choice.update(np.ones(2, bool))
    for k, single in enumerate(singles):
        initial = {key: value.clone() for key, value in single.choice.net.state_dict().items()}
        single.observe(Transition(obs[k], output[k], float(reward[k]), next_obs[k], False, float(discount[k])))
        single.choice.update(8, np.random.default_rng(0))
        mine = group.seed_state_dict(k)["choice"]["net"]
        for key, value in single.choice.net.state_dict().items():
            assert torch.allclose(mine[key], value, atol=1e-6), (k, key)
        assert not torch.equal(initial["4.weight"], mine["4.weight"])  # the update did move the gate
        stored = group.choice.replay.seed_rows(k)
        assert stored[2][0, 0] == (1.0 if gate[k] > 0 else 0.0)  # the choice: commit 1, defer 0


def test_a_seeds_state_is_an_ordinary_gate_checkpoint_and_a_left_out_seed_keeps_its_gate():
    group = GateTD3Group(learners([4, 5]))
    for step in range(6):
        group.observe(*transitions([4, 5], [1.0, -1.0] if step % 2 else [-1.0, 1.0]))
    before = group.choice.seed_state_dict(1)["net"]
    for _ in range(4):
        assert group.update(np.array([True, False])) is not None
    after = group.choice.seed_state_dict(1)["net"]
    assert all(torch.equal(before[key], after[key]) for key in before)
    obs = np.full((2, 3), 0.3, np.float32)
    for k, seed in enumerate([4, 5]):
        single = learners([seed])[0]
        single.load_state_dict(group.seed_state_dict(k))  # strict: every key and shape of a GateTD3 state
        assert single.act(obs[k], explore=False) == pytest.approx(group.act(obs, explore=False)[k], abs=1e-6)


def test_tempo_rl_in_a_group_stores_each_seeds_periods_and_partial_repetitions_as_its_own_learner():
    """Two seeds' decisions, one repeated over three periods (a path) and one of a single period: each
    seed's TD3 and skip replay rows are those its own `TempoRL.observe` stores, in the same order."""
    config = TempoRLConfig(hidden=(32, 16), batch_size=8, buffer_size=100, gamma=0.9)
    layout = OutputLayout(1, max_repeat=3)
    space = Box(np.array([-2.0, 1.0], np.float32), np.array([2.0, 3.0], np.float32))  # an action, then the count
    singles = [TempoRL(OBS, space, layout, config, seed) for seed in (0, 1)]
    group = TempoRLGroup(singles)
    rng = np.random.default_rng(2)
    obs, next_obs = rng.uniform(-1, 1, (2, 3)).astype(np.float32), rng.uniform(-1, 1, (2, 3)).astype(np.float32)
    output = np.array([[0.5, 3.0], [-1.0, 1.0]], np.float32)
    paths = [[(rng.uniform(-1, 1, 3).astype(np.float32), float(r), 1) for r in (1.0, -2.0)] + [(next_obs[0], 0.5, 1)],
             []]
    reward, terminated, discount = np.array([-0.5, 2.0]), np.array([True, False]), np.array([0.729, 0.9])
    group.observe(obs, output, reward, next_obs, terminated, discount, np.ones(2, bool), paths)
    for k, single in enumerate(singles):
        single.observe(Transition(obs[k], output[k], float(reward[k]), next_obs[k], bool(terminated[k]),
                                  float(discount[k]), tuple(paths[k])))
        for replay, buffer in ((group.td3.replay, single.td3.buffer), (group.choice.replay, single.choice.buffer)):
            mine = np.concatenate(replay.seed_rows(k), axis=1)
            theirs = single_rows(buffer)
            assert mine.shape == theirs.shape and np.allclose(mine, theirs), (k, mine.shape, theirs.shape)
    assert len(group.choice.replay.seed_rows(0)[0]) == 6 and len(group.td3.replay.seed_rows(1)[0]) == 1


def single_rows(buffer):
    """A single replay buffer's stored rows as the group lays them out: obs, action, reward, next, not done,
    discount (a skip's action holds its choice last, which the group keeps between action and reward)."""
    fields = buffer.fields()
    return np.concatenate([fields[key].numpy().reshape(len(buffer), -1) for key in buffer.FIELDS], axis=1)


def test_a_group_of_learners_started_from_weights_keeps_their_gates_moments_and_td3s_counts():
    """As a single run started from a checkpoint's weights keeps them (tests/test_td3_group.py: TD3's part)."""
    from conftest import assert_same_state

    trained = GateTD3Group(learners([4]))
    for step in range(6):
        trained.observe(*transitions([4], [1.0] if step % 2 else [-1.0]))
    for _ in range(4):
        trained.update(np.array([True]))
    state = trained.seed_state_dict(0)
    started = learners([0, 1])
    started[0].load_state_dict(state)
    group = GateTD3Group(started)
    assert_same_state(group.seed_state_dict(0)["choice"], state["choice"], "choice")
    assert_same_state(group.seed_state_dict(0)["td3"]["updates"], state["td3"]["updates"], "updates")
    assert group.seed_state_dict(1)["choice"]["opt"]["state"] == {}  # a new one's
