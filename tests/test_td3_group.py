"""TD3 for K seeds as one computation: each seed acts, learns and checkpoints as its own TD3 learner."""

import numpy as np
import pytest
import torch
from gymnasium.spaces import Box

from layered.buffer import Batch
from layered.learners.stacked import follow
from layered.learners.td3 import TD3, TD3Config
from layered.learners.td3_group import TD3Group
from layered.outputs import OutputLayout

OBS = Box(-1.0, 1.0, (3,), np.float32)
ACT = Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32))
CONFIG = TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100)


def learners(seeds, config=CONFIG):
    return [TD3(OBS, ACT, OutputLayout(2), config, seed) for seed in seeds]


def fill(group, seeds, steps=20, shift=0.0):
    """The same made-up transitions into the group's buffers, seed k's offset by k (and `shift` for seed 1)."""
    rng = np.random.default_rng(0)
    for _ in range(steps):
        obs = rng.uniform(-1, 1, (len(seeds), 3)).astype(np.float32) + np.arange(len(seeds))[:, None] * 0.1
        obs[1:2] += shift
        action = rng.uniform(ACT.low, ACT.high, (len(seeds), 2)).astype(np.float32)
        group.observe(obs, action, rng.normal(size=len(seeds)), obs * 0.5, rng.random(len(seeds)) < 0.1,
                      np.full(len(seeds), 0.99))


def test_a_group_acts_as_its_seeds_learners():
    singles = learners([0, 1, 2])
    group = TD3Group(singles)
    obs = np.random.default_rng(1).uniform(-1, 1, (3, 3)).astype(np.float32)
    acted = group.act(obs, explore=False)
    for k, single in enumerate(singles):
        assert acted[k] == pytest.approx(single.act(obs[k], explore=False), abs=1e-6)
    explored = group.act(obs, explore=True)
    assert np.all((explored >= ACT.low) & (explored <= ACT.high)) and not np.allclose(explored, acted)


@pytest.mark.parametrize("precision, rel, atol", [("float32", 1e-5, 1e-6), ("bfloat16", 2e-2, 1e-3)])
def test_one_update_of_the_group_is_each_seeds_own_update(precision, rel, atol):
    """In bfloat16 the batched and the single products round differently: equal within bf16's precision."""
    singles = learners([0, 1, 2], TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, precision=precision))
    group = TD3Group(singles)
    fill(group, [0, 1, 2])
    batch = group.sample()
    noise = torch.randn(batch[1].shape, generator=torch.Generator().manual_seed(3))
    critic = group.critic_step(batch, noise)
    actor = group.actor_step(batch[0])
    for k, single in enumerate(singles):
        mine = Batch(*(part[k] for part in batch))
        assert float(critic[k]) == pytest.approx(float(single._critic_step_eager(mine, noise[k])), rel=rel)
        assert float(actor[k]) == pytest.approx(float(single._actor_step_eager(mine.obs)), rel=rel)
        state = group.seed_state_dict(k)
        for part in ("actor", "critic", "actor_target", "critic_target"):
            theirs = getattr(single, part).state_dict()
            for key, value in theirs.items():
                assert torch.allclose(state[part][key], value, atol=atol), f"seed {k} {part}.{key}"


def test_seeds_never_mix():
    """Seed 0's update does not depend on what seed 1 stored (same group seed: same indices and noise)."""
    a, b = TD3Group(learners([0, 1])), TD3Group(learners([0, 1]))
    fill(a, [0, 1])
    fill(b, [0, 1], shift=0.5)
    for _ in range(4):
        a.update()
        b.update()
    assert all(torch.equal(x[0], y[0]) for x, y in zip(a.actor.parameters(), b.actor.parameters(), strict=True))
    assert not all(torch.equal(x[1], y[1]) for x, y in zip(a.actor.parameters(), b.actor.parameters(), strict=True))


def test_a_seeds_state_is_an_ordinary_td3_checkpoint():
    group = TD3Group(learners([4, 5]))
    fill(group, [4, 5])
    losses = [group.update() for _ in range(4)]
    assert [set(x) for x in losses] == [{"critic"}, {"critic", "actor"}] * 2 and losses[0]["critic"][0].shape == (2,)
    obs = np.full((2, 3), 0.3, np.float32)
    for k, seed in enumerate([4, 5]):
        single = learners([seed])[0]
        single.load_state_dict(group.seed_state_dict(k))  # strict: every key and shape of a TD3 state
        assert single.act(obs[k], explore=False) == pytest.approx(group.act(obs, explore=False)[k], abs=1e-6)
        assert single.updates == 4


def flat_state(group, k):
    """Every tensor of seed k's state (networks, targets, optimiser moments and counts), flattened."""
    state = group.seed_state_dict(k)
    out = {}
    for part in ("actor", "critic", "actor_target", "critic_target"):
        out |= {f"{part}.{key}": value for key, value in state[part].items()}
    for opt in ("actor_opt", "critic_opt"):
        for index, moments in state[opt]["state"].items():
            out |= {f"{opt}.{index}.{key}": value for key, value in moments.items()}
    return out


def test_a_seed_left_out_of_an_update_keeps_everything_and_the_others_do_not_notice():
    everyone, some = TD3Group(learners([0, 1, 2])), TD3Group(learners([0, 1, 2]))
    fill(everyone, [0, 1, 2])
    fill(some, [0, 1, 2])
    before = flat_state(some, 1)
    for _ in range(4):  # critic and actor steps, targets followed
        everyone.update()
        some.update(np.array([True, False, True]))
    assert list(some.updates) == [4, 0, 4]
    left_out = flat_state(some, 1)
    assert before.keys() == left_out.keys() and all(torch.equal(before[key], left_out[key]) for key in before)
    for k in (0, 2):
        mine, theirs = flat_state(some, k), flat_state(everyone, k)
        assert all(torch.equal(mine[key], theirs[key]) for key in mine), f"seed {k}"


def test_the_actor_waits_for_each_seeds_own_count_of_critic_updates():
    group = TD3Group(learners([0, 1], CONFIG.model_copy(update={"critic_warmup": 2})))
    fill(group, [0, 1])
    assert "actor" not in group.update(np.array([True, False]))
    assert "actor" not in group.update(np.array([True, True]))  # seed 0's 2nd update: still within its warm-up
    losses = group.update(np.array([True, True]))
    assert "actor" not in losses
    losses = group.update(np.array([True, True]))  # seed 0's 4th (acts), seed 1's 3rd (odd: critic only)
    assert list(losses["actor"][1]) == [True, False] and list(group.updates) == [4, 3]


def test_a_seed_state_loads_into_any_seed_of_a_group():
    trained, fresh = TD3Group(learners([0, 1])), TD3Group(learners([7, 8]))
    fill(trained, [0, 1])
    for _ in range(3):
        trained.update()
    fresh.load_seed_state_dict(1, trained.seed_state_dict(0))
    mine, theirs = flat_state(fresh, 1), flat_state(trained, 0)
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[key], theirs[key]) for key in mine)
    assert fresh.updates[1] == 3 and fresh.updates[0] == 0


def test_warm_up_actions_cover_each_seeds_range():
    group = TD3Group(learners([0, 1], CONFIG.model_copy(update={"warmup_range": 0.5})))
    actions = np.concatenate([group.random_action() for _ in range(200)])
    assert actions.shape == (400, 2)
    assert actions[:, 0].min() >= -1.0 and actions[:, 0].max() <= 1.0 and actions[:, 0].max() > 0.9
    assert actions[:, 1].min() >= 0.25 and actions[:, 1].max() <= 0.75


def test_bfloat16_rounds_the_groups_products_and_float32_does_not():
    groups = [TD3Group(learners([0, 1], TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, precision=p)),
                       seed=5) for p in ("float32", "float32", "bfloat16")]
    losses = []
    for group in groups:
        fill(group, [0, 1])
        losses.append(group.update()["critic"][0])
    assert torch.equal(losses[0], losses[1])
    assert not torch.equal(losses[0], losses[2]) and torch.allclose(losses[0], losses[2], rtol=5e-2)


def test_a_group_of_learners_started_from_weights_keeps_their_moments_and_counts():
    """As a single run started from a checkpoint's weights keeps its optimisers' moments and its update count."""
    from conftest import assert_same_state

    trained = TD3Group(learners([5]))
    fill(trained, [5])
    for _ in range(4):
        trained.update()
    state = trained.seed_state_dict(0)
    started = learners([0, 1])
    started[0].load_state_dict(state)
    group = TD3Group(started)
    mine = group.seed_state_dict(0)
    for part in ("actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt", "updates"):
        assert_same_state(mine[part], state[part], part)
    assert group.seed_state_dict(1)["critic_opt"]["state"] == {} and int(group.updates[1]) == 0  # a new one's


def test_a_soft_update_by_one_weight_for_every_seed_is_the_per_seed_one_bit_for_bit():
    """`follow` by a float (all layers in one operation) moves every seed as a [K] weight of that float does; a
    seed's 0 leaves it where it was."""
    torch.manual_seed(0)
    targets = [torch.zeros(3, 4, 2), torch.zeros(3, 1, 2)]
    sources = [torch.ones(3, 4, 2), torch.full((3, 1, 2), 3.0)]
    by_float = [t.clone() for t in targets]
    follow(by_float, sources, 0.25)
    assert torch.equal(by_float[0], torch.full((3, 4, 2), 0.25))  # 0 + 0.25 x (1 - 0)
    assert torch.equal(by_float[1], torch.full((3, 1, 2), 0.75))  # 0 + 0.25 x (3 - 0)
    noisy = [torch.randn(3, 4, 2), torch.randn(3, 1, 2)]
    each, one = [t.clone() for t in noisy], [t.clone() for t in noisy]
    follow(each, sources, torch.full((3,), 0.005))
    follow(one, sources, 0.005)
    assert all(torch.equal(a, b) for a, b in zip(each, one, strict=True))
    masked = [t.clone() for t in noisy]
    follow(masked, sources, torch.tensor([0.005, 0.0, 0.005]))
    assert all(torch.equal(m[1], n[1]) and torch.equal(m[0::2], o[0::2])
               for m, n, o in zip(masked, noisy, one, strict=True))
