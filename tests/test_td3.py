"""TD3: deterministic given a seed, save -> load gives identical behaviour, learns a simple target."""

import copy
import subprocess
import sys

import numpy as np
import pytest
import torch
from gymnasium.spaces import Box

from layered.combiners import Gate
from layered.buffer import Transition
from layered.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from layered.learners.td3 import TD3, TD3Config
from layered.outputs import OutputLayout

OBS = Box(-1.0, 1.0, (3,), np.float32)
ACT = Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32))
CONFIG = TD3Config(hidden=(32, 32), batch_size=16)


def filled(seed, n=64, config=CONFIG):
    learner = TD3(OBS, ACT, OutputLayout(2), config, seed)
    rng = np.random.default_rng(0)
    for _ in range(n):
        o = rng.uniform(-1, 1, 3).astype(np.float32)
        learner.observe(Transition(o, learner.random_action(), float(rng.normal()), o, False, 0.99))
    return learner


def test_actions_lie_in_the_box_with_and_without_noise():
    learner = filled(0)
    for explore in (False, True):
        for _ in range(50):
            a = learner.act(np.zeros(3, np.float32), explore)
            assert ACT.contains(a)


def test_same_seed_same_updates_and_actions():
    a, b = filled(1), filled(1)
    for _ in range(5):
        sa, sb = a.update(), b.update()
        assert sa == sb
    obs = np.ones(3, np.float32) * 0.3
    assert np.array_equal(a.act(obs, True), b.act(obs, True))
    assert not np.array_equal(filled(2).act(obs, False), a.act(obs, False))


def test_compute_of_one_action_is_the_actors_multiply_accumulates():
    # actor 3 -> 32 -> 32 -> 2
    assert filled(0).act_macs() == 3 * 32 + 32 * 32 + 32 * 2


def test_delayed_actor_updates():
    learner = filled(0)
    stats = [learner.update() for _ in range(4)]
    assert [set(s) for s in stats] == [{"critic"}, {"critic", "actor"}] * 2  # the actor every second update


def test_checkpoint_round_trip_gives_identical_behaviour(tmp_path):
    a = filled(3)
    for _ in range(4):
        a.update()
    save_checkpoint(tmp_path / "fast.pt", "fast", a.state_dict())
    b = filled(4)
    b.load_state_dict(load_checkpoint(tmp_path / "fast.pt", "fast"))
    obs = np.full(3, 0.2, np.float32)
    assert np.array_equal(a.act(obs, False), b.act(obs, False))
    b.buffer, b.rng = a.buffer, np.random.default_rng(9)
    a.rng = np.random.default_rng(9)
    assert a.update() == b.update()


def test_training_and_acting_from_a_checkpoint_import_no_compiler_and_a_loaded_state_takes_the_configured_rate(
        tmp_path):
    # making a torch optimiser imports torch's compiler (seconds of a command's start): a learner's Adam does not
    code = ("import sys, numpy as np; from gymnasium.spaces import Box; from layered.outputs import OutputLayout; "
            "from layered.buffer import Transition; from layered.learners.td3 import TD3, TD3Config; "
            "from layered.checkpoint import save_checkpoint; from pathlib import Path; "
            "act = Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32)); "
            "a = TD3(Box(-1.0, 1.0, (3,), np.float32), act, OutputLayout(2), "
            "TD3Config(hidden=(32, 32), batch_size=4), 3); o = np.zeros(3, np.float32); "
            "[a.observe(Transition(o, a.random_action(), 1.0, o, False, 0.99)) for _ in range(8)]; "
            "[a.update() for _ in range(4)]; save_checkpoint(Path(sys.argv[1]), 'fast', a.state_dict()); "
            "a.act(o, False); print('torch._dynamo' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "fast.pt")], capture_output=True, text=True,
                          check=True)
    assert done.stdout.split() == ["False"]
    saved = load_checkpoint(tmp_path / "fast.pt", "fast")
    b = TD3(OBS, ACT, OutputLayout(2), CONFIG.model_copy(update={"lr": 1e-4}), 4)
    b.load_state_dict(saved)
    loaded = b.state_dict()["critic_opt"]
    assert [g["lr"] for g in loaded["param_groups"]] == [1e-4]
    assert saved["critic_opt"]["state"].keys() == loaded["state"].keys()
    for key, moments in saved["critic_opt"]["state"].items():
        assert all(torch.equal(value, loaded["state"][key][name]) for name, value in moments.items())


def test_bad_checkpoints_are_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "x.pt", "x")
    (tmp_path / "x.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="not a checkpoint \\(damaged or of another program\\)"):
        load_checkpoint(tmp_path / "x.pt", "x")
    save_checkpoint(tmp_path / "y.pt", "slow", {"w": torch.zeros(1)})
    with pytest.raises(CheckpointError, match="not a checkpoint of 'fast'"):
        load_checkpoint(tmp_path / "y.pt", "fast")


def test_learns_the_best_action_of_a_one_step_problem():
    """Reward -(a - 0.5)^2 with no future: the greedy action must approach 0.5."""
    space = Box(-1.0, 1.0, (1,), np.float32)
    learner = TD3(OBS, space, OutputLayout(1), TD3Config(hidden=(32, 32), batch_size=64, lr=3e-3), seed=0)
    obs = np.zeros(3, np.float32)
    for _ in range(500):
        a = learner.random_action()
        learner.observe(Transition(obs, a, -float((a[0] - 0.5) ** 2), obs, True, 0.99))
    for _ in range(600):
        learner.update()
    assert learner.act(obs, False)[0] == pytest.approx(0.5, abs=0.1)


def test_temporl_learns_from_every_period_and_every_partial_repetition():
    from layered.learners.temporl import TempoRL, TempoRLConfig

    space = Box(np.array([-2.0, 1.0], np.float32), np.array([2.0, 4.0], np.float32))
    config = TempoRLConfig(hidden=(16,), batch_size=4, gamma=0.5)
    learner = TempoRL(OBS, space, OutputLayout(1, max_repeat=4), config, seed=0)
    states = [np.full(3, k, np.float32) for k in range(4)]
    path = tuple((states[k + 1], float(k + 1), 1) for k in range(3))  # rewards 1, 2, 3; one discount unit each
    learner.observe(Transition(states[0], np.array([0.3, 3.0], np.float32), 6.0, states[3], True, 0.5, path))
    assert len(learner.td3.buffer) == 3 and len(learner.choice.buffer) == 6  # 3 periods; 3 + 2 + 1 segments
    sb = learner.choice.buffer.fields()
    rows = {(int(sb["obs"][i, 0]), int(sb["action"][i, 1])): (float(sb["reward"][i, 0]), float(sb["discount"][i, 0]),
                                                              float(sb["not_done"][i, 0])) for i in range(6)}
    # keyed by (start state, choice index = length - 1)
    assert rows[(0, 2)] == (1 + 0.5 * 2 + 0.25 * 3, 0.125, 0.0)  # the whole skip ends the episode
    assert rows[(0, 1)] == (1 + 0.5 * 2, 0.25, 1.0)
    assert rows[(1, 0)] == (2.0, 0.5, 1.0)
    assert rows[(2, 0)] == (3.0, 0.5, 0.0)
    not_done = learner.td3.buffer.fields()["not_done"]
    assert float(not_done[2, 0]) == 0.0 and float(not_done[0, 0]) == 1.0
    action = learner.act(states[0], explore=True)
    assert space.contains(action) and action[1] in (1, 2, 3, 4)
    assert learner.update() is not None


def test_temporl_discounts_by_the_units_the_stack_gave_each_period():
    """train.discount = "step" at period 2: periods of 2, 2 and (the episode ending) 1 base steps."""
    from layered.learners.temporl import TempoRL, TempoRLConfig

    space = Box(np.array([-2.0, 1.0], np.float32), np.array([2.0, 4.0], np.float32))
    learner = TempoRL(OBS, space, OutputLayout(1, max_repeat=4), TempoRLConfig(hidden=(16,), gamma=0.5), seed=0)
    states = [np.full(3, k, np.float32) for k in range(4)]
    path = ((states[1], 1.0, 2), (states[2], 2.0, 2), (states[3], 3.0, 1))
    learner.observe(Transition(states[0], np.array([0.3, 3.0], np.float32), 6.0, states[3], True, 0.5**5, path))
    td3 = learner.td3.buffer.fields()["discount"][:, 0].tolist()
    assert td3 == [0.25, 0.25, 0.5]  # gamma**2 per full period, gamma for the last step
    sb = learner.choice.buffer.fields()
    rows = {(int(sb["obs"][i, 0]), int(sb["action"][i, 1])): (float(sb["reward"][i, 0]), float(sb["discount"][i, 0]))
            for i in range(6)}
    assert rows[(0, 2)] == (1 + 0.25 * 2 + 0.0625 * 3, 0.5**5)
    assert rows[(1, 1)] == (2 + 0.25 * 3, 0.125)


def test_gate_learner_proposes_an_action_and_a_gate_and_learns_which_pays():
    """Committing pays 1, deferring 0, with no future: the greedy gate must learn to commit."""
    from layered.learners.gate_td3 import GateTD3, GateTD3Config

    space = Box(np.array([-2.0, -1.0], np.float32), np.array([2.0, 1.0], np.float32))
    config = GateTD3Config(hidden=(32,), batch_size=64, lr=3e-3)
    learner = GateTD3(OBS, space, OutputLayout(1, gate_dims=1, gate=Gate.encoding), config, seed=0)
    obs = np.zeros(3, np.float32)
    for _ in range(400):
        a = learner.random_action()
        assert a[1] in (-1.0, 1.0)
        learner.observe(Transition(obs, a, 1.0 if a[1] > 0 else 0.0, obs, True, 0.99))
    assert len(learner.td3.buffer) == len(learner.choice.buffer) == 400
    for _ in range(300):
        learner.update()
    assert learner.act(obs, explore=False)[1] == 1.0
    assert learner.act_macs() == (3 * 32 + 32 * 1) + (4 * 32 + 32 * 2)


@pytest.mark.parametrize("head", ["min", "q1"])
def test_gate_bootstraps_from_the_chosen_head_of_the_target_critic(head):
    from layered.learners.gate_td3 import GateTD3, GateTD3Config

    space = Box(np.array([-2.0, -1.0], np.float32), np.array([2.0, 1.0], np.float32))
    config = GateTD3Config(hidden=(8,), gate_target=head)
    learner = GateTD3(OBS, space, OutputLayout(1, gate_dims=1, gate=Gate.encoding), config, seed=0)
    obs = torch.as_tensor(np.random.default_rng(0).uniform(-1, 1, (32, 3)), dtype=torch.float32)
    with torch.no_grad():
        q1, q2 = learner.td3.critic_target(obs, learner.td3.actor_target(obs))
    assert not torch.equal(q1, q2)  # two independently initialised heads
    expected = q1 if head == "q1" else torch.minimum(q1, q2)
    assert torch.equal(learner.choice.bootstrap(obs), expected)


def test_target_networks_keep_no_autograd_history():
    """The soft target update must not record autograd history: it would grow with every update."""
    learner = filled(0)
    for _ in range(6):
        learner.update()
    for net in (learner.actor_target, learner.critic_target):
        for p in net.parameters():
            assert not p.requires_grad and p.grad_fn is None and p.is_leaf


def test_a_zero_output_actor_starts_at_the_middle_of_its_range_and_then_learns():
    learner = TD3(OBS, ACT, OutputLayout(2), CONFIG.model_copy(update={"zero_output": True}), 0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        assert np.array_equal(learner.act(rng.uniform(-1, 1, 3).astype(np.float32), False), [0.0, 0.5])
    for _ in range(64):
        o = rng.uniform(-1, 1, 3).astype(np.float32)
        learner.observe(Transition(o, learner.random_action(), float(rng.normal()), o, False, 0.99))
    for _ in range(4):
        learner.update()
    assert not np.array_equal(learner.act(np.ones(3, np.float32), False), [0.0, 0.5])


def test_the_actor_waits_for_the_critic_warmup_while_the_critic_targets_follow():
    learner = filled(7, config=CONFIG.model_copy(update={"critic_warmup": 4}))
    actor = copy.deepcopy(learner.actor.state_dict())
    actor_target = copy.deepcopy(learner.actor_target.state_dict())
    critic_target = copy.deepcopy(learner.critic_target.state_dict())
    for _ in range(4):  # updates 2 and 4 would move the actor without the warm-up
        assert "actor" not in learner.update()
    assert all(torch.equal(v, learner.actor.state_dict()[k]) for k, v in actor.items())
    assert all(torch.equal(v, learner.actor_target.state_dict()[k]) for k, v in actor_target.items())
    moved = [not torch.equal(v, learner.critic_target.state_dict()[k]) for k, v in critic_target.items()]
    assert all(moved)  # two soft updates of the critic's targets, at updates 2 and 4
    assert "actor" not in learner.update() and "actor" in learner.update()  # update 6 is the first
    assert not torch.equal(actor["net.0.weight"], learner.actor.state_dict()["net.0.weight"])


def test_an_anchored_actor_stays_near_the_middle_of_its_range():
    """Rewards that grow with the first action dimension pull the actor up; the anchor holds it back."""
    def trained(anchor):
        learner = TD3(OBS, ACT, OutputLayout(2), CONFIG.model_copy(update={"actor_anchor": anchor, "lr": 3e-3}), 0)
        rng = np.random.default_rng(0)
        for _ in range(256):
            o, a = rng.uniform(-1, 1, 3).astype(np.float32), learner.random_action()
            learner.observe(Transition(o, a, float(a[0]), o, True, 0.99))
        for _ in range(200):
            learner.update()
        return learner.act(np.zeros(3, np.float32), explore=False)

    free, anchored = trained(0.0), trained(10.0)
    assert free[0] > 1.5  # towards the top of [-2, 2]
    # Q = a0 (one terminal step). In a0 the value's term -Q / mean|Q| pulls with 1 / a0 and the anchor's
    # 10 * mean(((a - middle) / half)²) pushes back with 10 * a0 / 4: they balance at a0 = 2 / sqrt(10) = 0.632.
    # Nothing pulls a1, which the anchor holds at 0.5, the middle of [0, 1].
    assert anchored[0] == pytest.approx(2 / np.sqrt(10), abs=0.08)
    assert anchored[1] == pytest.approx(0.5, abs=0.05)


def test_compiled_steps_give_the_eager_updates():
    eager, inductor = filled(5), filled(5, config=CONFIG.model_copy(update={"compile": "inductor"}))
    for _ in range(4):
        a, b = eager.update(), inductor.update()
        assert a["critic"].item() == pytest.approx(b["critic"].item(), rel=1e-5)
        assert set(a) == set(b)
    obs = np.full(3, 0.2, np.float32)
    assert np.allclose(eager.act(obs, False), inductor.act(obs, False), atol=1e-5)


def test_cuda_graphs_need_a_gpu_device():
    with pytest.raises(ValueError, match="compile = 'cudagraphs' needs the learner on a GPU"):
        TD3Config(compile="cudagraphs", device="cpu")


def test_bfloat16_updates_keep_float32_weights_and_come_close_to_float32_losses():
    full, half = (filled(6, config=CONFIG.model_copy(update={"precision": p})) for p in ("float32", "bfloat16"))
    a, b = full.update(), half.update()
    full_loss, half_loss = a["critic"].item(), b["critic"].item()
    assert half_loss == pytest.approx(full_loss, rel=0.05) and half_loss != full_loss
    assert all(p.dtype == torch.float32 for p in (*half.actor.parameters(), *half.critic.parameters()))
