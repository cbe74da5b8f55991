"""The AEC agent view: PettingZoo conformance and the rewards and timing each layer receives."""

import gymnasium as gym
import numpy as np
import pytest
from conftest import stack_recipe
from pettingzoo.test import api_test

from layered import make_aec_env

DEPTHS = {1: [1], 2: [4, 1], 3: [4, 2, 1], 4: [8, 4, 2, 1]}


@pytest.mark.parametrize("kind", ["residual-clip", "gate"])
@pytest.mark.parametrize("depth", [1, 2, 3, 4])
def test_pettingzoo_api(depth, kind):
    env = make_aec_env(stack_recipe(DEPTHS[depth], kind), seed=0)
    api_test(env, num_cycles=300)
    env.close()


def test_pettingzoo_api_with_a_layer_that_learns_from_a_gates_commits():
    recipe = stack_recipe([4, 1], "gate")
    layers = [recipe.layers[0], recipe.layers[1].model_copy(update={"learn_from_commits": True})]
    env = make_aec_env(recipe.model_copy(update={"layers": layers}), seed=0)
    api_test(env, num_cycles=300)
    env.close()


@pytest.mark.parametrize("settings", [
    {"delay": 1}, {"delay": 2, "sees_in_flight": True}, {"delay": 1, "sees_executed": True}, {"max_repeat": 3},
], ids=["delay", "delay-2-sees-in-flight", "delay-sees-executed", "repeats"])
def test_pettingzoo_api_with_delays_and_repeats(settings):
    """The observation and action spaces that delays and repeats extend (outputs in flight, a repeat count)."""
    recipe = stack_recipe([4, 1], "residual-clip")
    layers = [layer.model_copy(update=settings) for layer in recipe.layers]
    env = make_aec_env(recipe.model_copy(update={"layers": layers}), seed=0)
    api_test(env, num_cycles=300)
    env.close()


def test_pettingzoo_api_mixed_combiners_on_mujoco():
    env = make_aec_env(stack_recipe([4, 2, 1], ["gate", "residual-clip", "residual-clip"], env="InvertedPendulum-v5"))
    api_test(env, num_cycles=200)
    env.close()


def test_a_slow_layers_reward_is_the_sum_over_its_period_and_info_has_the_span():
    env = make_aec_env(stack_recipe([4]), seed=3)
    plain = gym.make("Pendulum-v1")
    plain.reset(seed=3)
    action = np.array([0.7], np.float32)
    expected = [sum(plain.step(action)[1] for _ in range(4)) for _ in range(2)]
    got = []
    for _ in env.agent_iter(max_iter=3):
        _, reward, _, _, info = env.last()
        got.append((reward, info.get("elapsed")))
        env.step(action)
    assert got[0] == (0.0, None)  # no decision yet, so no transition to hand over
    assert [r for r, _ in got[1:]] == pytest.approx(expected, rel=1e-6)
    assert [k for _, k in got[1:]] == [4, 4]


def test_only_due_layers_are_yielded_and_a_committed_gate_silences_the_fast_layer():
    env = make_aec_env(stack_recipe([4, 1], "gate"), seed=0)
    commit, defer = np.array([0.5, 1.0], np.float32), np.array([0.5, -1.0], np.float32)
    fast = np.array([0.1], np.float32)
    order = []
    for name in env.agent_iter(max_iter=8):
        order.append((env.stack.t, name))
        gate_out = commit if env.stack.t < 4 else defer
        env.step(gate_out if name == "l0" else fast)
    assert order[:5] == [(0, "l0"), (4, "l0"), (4, "l1"), (5, "l1"), (6, "l1")]


def test_a_layer_first_asked_after_a_gate_committed_has_no_reward_from_before_its_first_decision():
    env = make_aec_env(stack_recipe([4, 1], "gate"), seed=0)
    commit, defer = np.array([0.5, 1.0], np.float32), np.array([0.5, -1.0], np.float32)
    firsts = {}
    for name in env.agent_iter(max_iter=4):
        _, reward, _, _, info = env.last()
        firsts.setdefault(name, (env.stack.t, reward, "transition" in info))
        env.step((commit if env.stack.t < 4 else defer) if name == "l0" else np.array([0.1], np.float32))
    assert firsts == {"l0": (0, 0.0, False), "l1": (4, 0.0, False)}  # steps 0-3 were the gate's alone


def test_episode_end_reports_truncation_to_every_layer_then_removes_them():
    env = make_aec_env(stack_recipe([4, 2, 1]), seed=0)
    finals = {}
    for name in env.agent_iter():
        _, _, terminated, truncated, _ = env.last()
        if terminated or truncated:
            finals[name] = (terminated, truncated)
            env.step(None)
        else:
            env.step(env.action_space(name).sample())
    assert finals == {n: (False, True) for n in ("l0", "l1", "l2")}
    assert env.episode_steps == 200 and env.agents == []


def test_same_seed_same_trajectory():
    def rollout(seed):
        env = make_aec_env(stack_recipe([4, 1], "gate"), seed=seed, keep_trace=True)
        for name in env.agent_iter():
            _, _, term, trunc, _ = env.last()
            space = env.action_space(name)
            obs = env.observe(name)
            env.step(None if term or trunc else np.tanh(obs[: space.shape[0]] * 3).astype(np.float32))
        return np.array([(s.reward, *s.action) for s in env.trace]), [s.decided for s in env.trace]

    a1, d1 = rollout(5)
    a2, d2 = rollout(5)
    assert np.array_equal(a1, a2) and d1 == d2
    assert not np.array_equal(a1, rollout(6)[0])


def test_a_loop_sampling_the_layers_action_spaces_repeats_itself_given_the_seed():
    """The README's loop: each layer's action space is seeded from the env's seed at reset."""
    def rollout(seed):
        env = make_aec_env(stack_recipe([4, 1], "gate"), seed=seed, keep_trace=True)
        for name in env.agent_iter():
            _, _, term, trunc, _ = env.last()
            env.step(None if term or trunc else env.action_space(name).sample())
        return np.array([s.action for s in env.trace])

    assert np.array_equal(rollout(3), rollout(3)) and not np.array_equal(rollout(3), rollout(4))


def test_misuse_of_the_agent_view_is_one_clear_error_naming_the_layer():
    env = make_aec_env(stack_recipe([4, 1]), seed=0)
    with pytest.raises(ValueError, match=r"layer 'l0' was given an output of shape \(3,\); its action space .* takes "
                                         r"1 number$"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"layer 'l0' was given a non-finite action \[nan\]"):
        env.step(np.array([np.nan], np.float32))
    with pytest.raises(ValueError, match="non-finite action \\[inf\\]"):
        env.step(np.array([np.inf], np.float32))
    for _ in env.agent_iter():
        _, _, term, trunc, _ = env.last()
        env.step(None if term or trunc else np.zeros(1, np.float32))
    with pytest.raises(RuntimeError, match="the episode has ended: reset the env before stepping it again"):
        env.step(np.zeros(1, np.float32))
    with pytest.raises(RuntimeError, match="the episode has ended: reset the env"):
        env.last()


def test_a_repeating_layer_gets_the_observation_and_reward_of_each_period_it_held():
    recipe = stack_recipe([1])
    recipe = recipe.model_copy(update={"layers": [recipe.layers[0].model_copy(update={"max_repeat": 4})]})
    env = make_aec_env(recipe, seed=2)
    plain = gym.make("Pendulum-v1")
    plain.reset(seed=2)
    env.step(np.array([1.0, 3.0], np.float32))  # hold 1.0 for three steps
    expected = [plain.step(np.array([1.0], np.float32))[:2] for _ in range(3)]
    _, reward, _, _, info = env.last()
    path = info["transition"].path
    assert info["elapsed"] == 3 and len(path) == 3
    for (o, r, units), (eo, er) in zip(path, expected, strict=True):
        assert o == pytest.approx(eo, rel=1e-5) and r == pytest.approx(er) and units == 1  # one per period
    assert reward == pytest.approx(sum(r for _, r in expected)) == info["transition"].reward
