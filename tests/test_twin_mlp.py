"""TD3's two critics of K seeds as one stack: each seed's twins compute what its own two networks do."""

import numpy as np
import pytest
import torch
from gymnasium.spaces import Box

from layered.learners.stacked import StackedAdam, StackedMLP, TwinMLP
from layered.learners.td3 import TD3, TD3Config, mlp
from layered.learners.td3_group import TD3Group
from layered.outputs import OutputLayout

K, BATCH, SIZES = 3, 5, (4, 8, 6, 1)


def critics(seed):
    """K seeds' first and second critics, each an ordinary MLP."""
    torch.manual_seed(seed)
    return [mlp(SIZES) for _ in range(K)], [mlp(SIZES) for _ in range(K)]


def test_each_seeds_twins_compute_its_own_two_networks():
    firsts, seconds = critics(0)
    twin = TwinMLP(firsts, seconds)
    x = torch.randn(K, BATCH, SIZES[0])
    both = twin(x)
    assert both.shape == (K, 2, BATCH, 1)
    for k in range(K):
        torch.testing.assert_close(both[k, 0], firsts[k](x[k]), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(both[k, 1], seconds[k](x[k]), rtol=1e-5, atol=1e-6)
    # as two stacks of one network per seed compute them, bit for bit; `first` alone the first stack's
    assert torch.equal(both[:, 0], StackedMLP(firsts)(x)) and torch.equal(both[:, 1], StackedMLP(seconds)(x))
    assert torch.equal(twin(x, first=True), both[:, 0])


def test_chosen_seeds_compute_alone_and_frozen_twins_take_no_gradient():
    twin = TwinMLP(*critics(1))
    x = torch.randn(K, BATCH, SIZES[0])
    seeds = torch.tensor([2, 0])
    assert torch.equal(twin(x[seeds], seeds=seeds), twin(x)[seeds])
    frozen = twin(x.requires_grad_(), frozen=True, first=True).sum()
    frozen.backward()
    assert x.grad is not None and all(p.grad is None for p in twin.parameters())


def test_a_seeds_twins_are_a_critics_state_and_load_back_into_any_seed():
    firsts, seconds = critics(2)
    twin = TwinMLP(firsts, seconds)
    state = twin.seed_state(1, ("q1.", "q2."))
    expected = {f"q1.{key}": value for key, value in firsts[1].state_dict().items()}
    expected |= {f"q2.{key}": value for key, value in seconds[1].state_dict().items()}
    assert state.keys() == expected.keys()
    for key, value in expected.items():
        assert torch.equal(state[key], value)
    other = TwinMLP(*critics(3))
    other.load_seed_state(0, state, ("q1.", "q2."))
    x = torch.randn(1, BATCH, SIZES[0])
    assert torch.equal(other(x.expand(K, -1, -1))[0], twin(x.expand(K, -1, -1))[1])


@pytest.mark.parametrize("seed", [0, 2])
def test_twin_adam_keeps_a_seeds_moments_as_one_adam_of_both_networks_does(seed):
    """A seed's moments and counts in a single network's layout: the first twin's parameters, then the second's."""
    firsts, seconds = critics(4)
    twin = TwinMLP(firsts, seconds)
    single = [*firsts[seed].parameters(), *seconds[seed].parameters()]
    reference = torch.optim.Adam(single, lr=1e-3, fused=True)
    adam = StackedAdam(list(twin.parameters()), 1e-3, K, reference.state_dict(), twins=True)
    x = torch.randn(K, BATCH, SIZES[0])
    twin(x).square().sum().backward()
    (firsts[seed](x[seed]).square().sum() + seconds[seed](x[seed]).square().sum()).backward()
    adam.step(np.ones(K, bool))
    reference.step()
    state, expected = adam.seed_state(seed)["state"], reference.state_dict()["state"]
    assert state.keys() == expected.keys() == set(range(len(single)))
    for index, moments in expected.items():
        assert float(state[index]["step"]) == float(moments["step"]) == 1.0
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(state[index][key], moments[key], rtol=1e-5, atol=1e-7)
    fresh = StackedAdam(list(TwinMLP(*critics(5)).parameters()), 1e-3, K, reference.state_dict(), twins=True)
    fresh.load_seed_state(1, adam.seed_state(seed))
    for index, moments in fresh.seed_state(1)["state"].items():
        assert torch.equal(moments["exp_avg"], state[index]["exp_avg"])


def test_twin_adam_steps_each_twin_as_the_adam_of_two_stacks_does_bit_for_bit():
    """Each twin is a tensor of its own to fused Adam, as each network of two stacks is: the kernel rounds a
    tensor's tail apart from its whole vectors, so handing it both twins as one tensor would round otherwise."""
    torch.manual_seed(6)
    sizes = (4, 20, 12, 1)  # (widths whose twins together cross a vector's length where one alone does not)
    firsts, seconds = [mlp(sizes) for _ in range(K)], [mlp(sizes) for _ in range(K)]
    twin, one, two = TwinMLP(firsts, seconds), StackedMLP(firsts), StackedMLP(seconds)
    template = torch.optim.Adam(mlp(sizes).parameters(), lr=1e-3).state_dict()
    twin_adam = StackedAdam(list(twin.parameters()), 1e-3, K, template, twins=True)
    stacks_adam = StackedAdam([*one.parameters(), *two.parameters()], 1e-3, K, template)
    rows = np.array([True, False, True])
    for _ in range(3):
        for p, q, r in zip(twin.parameters(), one.parameters(), two.parameters(), strict=True):
            grad = torch.randn_like(p) * 1e-3
            p.grad, q.grad, r.grad = grad.clone(), grad[:, 0].clone(), grad[:, 1].clone()
        twin_adam.step(rows)
        stacks_adam.step(rows)
    n = len(twin_adam.params)
    for mine, theirs in ((twin_adam.params, stacks_adam.params), (twin_adam.exp_avg, stacks_adam.exp_avg),
                         (twin_adam.exp_avg_sq, stacks_adam.exp_avg_sq)):
        for j, t in enumerate(mine):
            assert torch.equal(t[:, 0], theirs[j]) and torch.equal(t[:, 1], theirs[n + j])


def test_a_group_whose_critics_were_two_stacks_resumes_as_the_twins():
    """A group checkpoint of before the twins (`q1`, `q2` and their targets; Adam's moments the first's, then the
    second's) loads into the one stack and goes on as the group it was taken from."""
    obs, act, config = Box(-1.0, 1.0, (3,), np.float32), Box(-1.0, 1.0, (1,), np.float32), TD3Config(
        hidden=(12, 20), batch_size=8, buffer_size=50)
    groups = [TD3Group([TD3(obs, act, OutputLayout(1), config, seed) for seed in (0, 1)]) for _ in range(2)]
    rng = np.random.default_rng(0)
    for _ in range(20):
        o = rng.uniform(-1, 1, (2, 3)).astype(np.float32)
        for group in groups:
            group.observe(o, o[:, :1], np.ones(2), o, np.zeros(2, bool), np.full(2, 0.99))
    for _ in range(3):
        groups[0].update()
    state = groups[0].resume_state()
    nets = {name: net for name, net in state["nets"].items() if "critic" not in name}
    for twins, names in (("critic", ("q1", "q2")), ("critic_target", ("q1_target", "q2_target"))):
        for i, name in enumerate(names):
            nets[name] = {key: t[:, i].clone() for key, t in state["nets"][twins].items()}
    opt = state["critic_opt"]
    old = {**state, "nets": nets, "critic_opt": {**opt, **{key: [t[:, i].clone() for i in (0, 1) for t in opt[key]]
                                                            for key in ("exp_avg", "exp_avg_sq")}}}
    groups[1].load_resume_state(old)
    losses = [group.update()["critic"][0] for group in groups]
    assert torch.equal(*losses)
    for a, b in zip(groups[0].critic_opt.exp_avg_sq + list(groups[0].critic.parameters()),
                    groups[1].critic_opt.exp_avg_sq + list(groups[1].critic.parameters()), strict=True):
        assert torch.equal(a, b)
