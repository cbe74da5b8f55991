"""The learners with their update captured (`td3`, `temporl`, `td3-gate`) train as a group of one seed:
acting, storing and updating through it, their state dicts a plain learner's, and a run through them resuming
exactly. On a CPU the group runs eagerly (`captures` stood in for), so what is checked here is the learners'
plumbing; the capture itself is the group's (tests/test_graphed.py, and test_device.py's compiled learners on a
GPU)."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import assert_same_run, assert_same_state, stop_at_episode_end

import layered.learners.captured as captured_learners
from layered import load_recipe
from layered.buffer import Transition
from layered.checkpoint import load_checkpoint
from layered.interrupt import Stopped
from layered.learner_set import build_learners
from layered.learners import LEARNERS
from layered.learners.td3 import TD3, TD3Config
from layered.learners.captured import CapturedGateTD3, CapturedTD3, CapturedTempoRL, GroupOfOne
from layered.learners.td3_group import TD3Group
from layered.outputs import OutputLayout
from layered.runs import train

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"
OBS = gym.spaces.Box(-8.0, 8.0, (3,), np.float32)
ACTION = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
CONFIG = TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, critic_warmup=2)


@pytest.fixture
def captured(monkeypatch):
    """`td3` learners train through a group of one here, as they do on a GPU with compile = "cudagraphs"."""
    monkeypatch.setattr(captured_learners, "captures", lambda config, device: True)


def learner(cls: type[TD3] = CapturedTD3, seed: int = 4) -> TD3:
    return cls(OBS, ACTION, OutputLayout(1), CONFIG, seed)


def transitions(n: int, seed: int = 0) -> list[Transition]:
    rng = np.random.default_rng(seed)
    return [Transition(rng.normal(size=3).astype(np.float32), rng.uniform(-2, 2, 1).astype(np.float32),
                       float(rng.normal()), rng.normal(size=3).astype(np.float32), bool(rng.random() < 0.1), 0.99)
            for _ in range(n)]


def test_td3_is_the_captured_learner_and_without_a_capture_it_is_td3_as_it_is():
    assert [LEARNERS.get(kind) for kind in ("td3", "temporl", "td3-gate")] == [CapturedTD3, CapturedTempoRL,
                                                                              CapturedGateTD3]
    plain, mine = learner(TD3), learner()
    assert mine.group is None
    for t in transitions(20):
        plain.observe(t)
        mine.observe(t)
    for _ in range(5):
        a, b = plain.update(), mine.update()
        assert a is not None and b is not None and a.keys() == b.keys()
        assert all(torch.equal(a[name], b[name]) for name in a)
    obs = transitions(1)[0].obs
    assert np.array_equal(plain.act(obs, explore=True), mine.act(obs, explore=True))


def test_with_its_update_captured_it_acts_stores_and_updates_as_a_group_of_one(captured):
    mine, group = learner(), TD3Group([learner(TD3)], seed=4)
    assert isinstance(mine.group, TD3Group) and mine.group.k == 1
    for t in transitions(30):
        mine.observe(t)
        group.observe(t.obs[None], t.action[None], np.array([t.reward]), t.next_obs[None], np.array([t.terminated]),
                      np.array([t.discount]))
    for _ in range(6):  # the critic's warm-up, then the actor's delayed steps
        a, b = mine.update(), group.update()
        assert a is not None and b is not None and a.keys() == b.keys()
        assert all(a[name].shape == () and torch.equal(a[name], b[name][0][0]) for name in a)
    obs = transitions(1, seed=1)[0].obs
    for explore in (False, True):
        assert np.array_equal(mine.act(obs, explore), group.act(obs[None], explore)[0])


def test_weights_loaded_make_no_group_and_go_on_into_the_group_made_later(captured):
    """A group of many seeds loads weights into its seeds' learners before stacking them: they make no group of
    one (and no replay buffer) of their own; a learner's group, once made, holds what was loaded."""
    trained = learner()
    for t in transitions(30):
        trained.observe(t)
    for _ in range(4):
        trained.update()
    started = learner(seed=9)
    started.load_state_dict(trained.state_dict())
    assert started._group is None
    assert_same_state(started.state_dict(), trained.state_dict(), "loaded")  # (held by its own networks)
    assert started.group is not None
    mine, theirs = started.state_dict(), trained.state_dict()
    for part in ("actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt", "updates"):
        assert_same_state(mine[part], theirs[part], part)


def test_its_state_dicts_are_a_plain_td3s_both_ways(captured):
    mine = learner()
    for t in transitions(30):
        mine.observe(t)
    for _ in range(5):
        mine.update()
    plain = learner(TD3, seed=9)
    plain.load_state_dict(mine.state_dict())
    obs = np.stack([t.obs for t in transitions(8, seed=2)])
    greedy = [mine.act(o, explore=False) for o in obs]
    assert np.allclose(greedy, [plain.act(o, explore=False) for o in obs], atol=1e-6)
    policy = mine.policy()  # the group's weights, as an exported module has them
    assert np.allclose(greedy, policy(torch.from_numpy(obs)).numpy(), atol=1e-6)
    again = learner(seed=9)
    again.load_state_dict(plain.state_dict())  # a plain TD3's checkpoint, started from
    assert np.array_equal(greedy, [again.act(o, explore=False) for o in obs])
    assert again.group is not None and mine.group is not None
    assert int(again.group.updates[0]) == int(mine.group.updates[0]) == 5  # its count, through a plain TD3's


TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50", "eval.every=150", "eval.episodes=1",
        "eval.fresh_episodes=1"]


@pytest.mark.parametrize("name", ["td3.toml", "temporl.toml", "tla-joint.toml"])  # TD3, TempoRL, the joint gate
def test_a_run_through_them_stopped_at_an_episode_end_resumes_to_the_same_files(name, captured, tmp_path,
                                                                                  monkeypatch):
    recipe = load_recipe(PENDULUM / name, TINY)
    built = build_learners(recipe)
    assert all(isinstance(lr, GroupOfOne) and lr.group is not None for lr in built.values())  # (as the run's are)
    train(recipe, tmp_path / "whole", max_steps=600, progress=False, label="x")
    for layer, mine in built.items():  # each layer's final checkpoint a plain learner's
        final = load_checkpoint(tmp_path / "whole" / "checkpoints" / f"{layer}.pt", layer)
        plain = type(mine).Single(mine.obs_space, mine.action_space, mine.layout, mine.config, 0)
        plain.load_state_dict(final)
    stop_at_episode_end(monkeypatch, 2)
    out = tmp_path / "stopped"
    with pytest.raises(Stopped):
        train(recipe, out, max_steps=600, progress=False, label="x")
    monkeypatch.undo()
    monkeypatch.setattr(captured_learners, "captures", lambda config, device: True)
    train(recipe, out, max_steps=600, progress=False, label="x", resume=True)
    assert_same_run(tmp_path / "whole", out)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")
def test_a_captured_run_on_the_gpu_trains_through_a_group_of_one_and_resumes_to_the_same_files(tmp_path, monkeypatch):
    recipe = load_recipe(PENDULUM / "td3.toml", [*TINY, "learner.device=cuda", "learner.compile=cudagraphs"])
    built = build_learners(recipe)[recipe.layers[0].name]
    assert isinstance(built, CapturedTD3) and built.group is not None
    train(recipe, tmp_path / "whole", max_steps=600, progress=False, label="x")
    stop_at_episode_end(monkeypatch, 2)
    with pytest.raises(Stopped):
        train(recipe, tmp_path / "stopped", max_steps=600, progress=False, label="x")
    monkeypatch.undo()
    train(recipe, tmp_path / "stopped", max_steps=600, progress=False, label="x", resume=True)
    assert_same_run(tmp_path / "whole", tmp_path / "stopped")


@pytest.mark.parametrize("name", ["td3.toml", "temporl.toml", "tla-joint.toml"])
def test_their_own_buffers_stay_on_the_host_unwritten_where_the_group_keeps_the_replay(name, captured):
    for mine in build_learners(load_recipe(PENDULUM / name, TINY)).values():
        own = list(super(GroupOfOne, mine).replays.values())  # (the single learner's buffers)
        assert own and all(buffer.device.type == "cpu" for buffer in own)
        assert mine.replays.keys() == {"td3", "choice"} if len(own) == 2 else {"td3"}
        assert all(theirs is not buffer for theirs in mine.replays.values() for buffer in own)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")
def test_a_captured_learner_on_the_gpu_keeps_one_replay_there():
    config = TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, device="cuda", compile="cudagraphs")
    single = CapturedTD3(OBS, ACTION, OutputLayout(1), config, 0)
    assert single.buffer._rows.device.type == "cpu" and single.group.replay._rows.device.type == "cuda"
