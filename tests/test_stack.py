"""Stack semantics by hand: who decides when, how held outputs merge, what each layer is paid."""

import numpy as np
import pytest
from conftest import stack_recipe
from gymnasium.spaces import Box

from layered.combiners import Route
from layered.stack import Stack

OBS = Box(-1.0, 1.0, (3,), np.float32)
ACT = Box(-2.0, 2.0, (1,), np.float32)


def make(periods, kinds="residual-clip", **kw):
    extra = {k: kw.pop(k) for k in list(kw) if k in ("combine",)}
    return Stack(stack_recipe(periods, kinds, **extra), OBS, ACT, **kw)


def decisions_at(stack, outputs):
    """Layers that decide at the current step, each holding the given output once it decides."""
    order, i = [], stack.next_due(0)
    while i is not None:
        order.append(i)
        stack.hold(i, outputs[i])
        i = stack.next_due(i + 1)
    return order


def test_each_layer_decides_on_multiples_of_its_period_slowest_first():
    stack = make([4, 2, 1])
    outs = [np.zeros(1)] * 3
    schedule = []
    for _ in range(8):
        schedule.append(decisions_at(stack, outs))
        stack.tick()
    assert schedule == [[0, 1, 2], [2], [1, 2], [2], [0, 1, 2], [2], [1, 2], [2]]


def test_a_committed_gate_blocks_the_layers_below_for_its_period():
    stack = make([4, 1], "gate")
    commit, defer, fast = np.array([1.0, 0.5]), np.array([1.0, -0.5]), np.array([0.3])
    assert decisions_at(stack, [commit, fast]) == [0]
    for _ in range(3):
        stack.tick()
        assert stack.next_due(0) is None
    stack.tick()
    assert decisions_at(stack, [defer, fast]) == [0, 1]
    stack.tick()
    assert decisions_at(stack, [defer, fast]) == [1]


def test_residual_stack_sums_held_outputs_and_clips_once():
    stack = make([4, 2, 1])
    for i, a in enumerate([1.5, 0.4, 0.3]):
        stack.hold(i, np.array([a]))
    c = stack.compose()
    assert c.action == pytest.approx([2.0])  # clip(1.5 + 0.4 + 0.3)
    assert [float(c.contributions[i][0]) for i in range(3)] == pytest.approx([1.5, 0.4, 0.3])


def test_evaluation_threshold_drops_small_residual_contributions():
    # threshold 0.3 x max action 2 = 0.6; l1's effect 0.5 is dropped, l2's effect 0.7 is kept
    stack = make([4, 2, 1], evaluation=True)
    for i, a in enumerate([1.0, 0.5, 0.7]):
        stack.hold(i, np.array([a]))
    c = stack.compose()
    assert c.action == pytest.approx([1.7])
    assert float(c.contributions[1][0]) == 0.0


def test_threshold_override_and_training_mode():
    for kw, expected in [({"evaluation": True, "threshold": 0.1}, 1.5), ({"evaluation": False}, 1.5)]:
        stack = make([2, 1], **kw)
        stack.hold(0, np.array([1.0]))
        stack.hold(1, np.array([0.5]))  # effect 0.5 >= 0.2 (override) and no threshold in training
        assert stack.compose().action == pytest.approx([expected])


def test_gate_over_residual_layers():
    stack = make([4, 2, 1], ["gate", "residual-clip", "residual-clip"])
    stack.hold(1, np.array([0.5]))
    stack.hold(2, np.array([0.25]))
    stack.hold(0, np.array([1.0, 1.0]))
    c = stack.compose()
    assert c.action == pytest.approx([1.0]) and set(c.contributions) == {0}
    assert c.routes[0] is Route.COMMIT
    stack.hold(0, np.array([1.0, -1.0]))
    c = stack.compose()
    assert c.action == pytest.approx([0.75])  # the gate defers: its own action is left out
    assert float(c.contributions[0][0]) == 0.0


def test_residual_over_gate_layers():
    stack = make([4, 2, 1], ["residual-clip", "gate", "residual-clip"])
    stack.hold(0, np.array([1.0]))
    stack.hold(2, np.array([0.3]))
    stack.hold(1, np.array([0.5, 1.0]))
    assert stack.compose().action == pytest.approx([1.5])  # slow + committed mid
    stack.hold(1, np.array([0.5, -1.0]))
    assert stack.compose().action == pytest.approx([1.3])  # slow + fast in place of mid


def test_absent_layers_contribute_nothing_and_never_decide():
    stack = make([4, 2, 1], active=["l0", "l2"])
    assert decisions_at(stack, [np.array([1.0]), np.array([9.0]), np.array([0.25])]) == [0, 2]
    assert stack.compose().action == pytest.approx([1.25])


def test_an_absent_gate_defers_and_the_fastest_present_layer_just_acts():
    stack = make([4, 1], "gate", active=["l1"])
    stack.hold(1, np.array([-0.5]))
    assert stack.compose().action == pytest.approx([-0.5])


def test_action_spaces_residual_range_is_scaled_and_gates_add_a_dimension():
    recipe = stack_recipe([4, 1], "residual-clip")
    fast = recipe.layers[1].model_copy(update={"action_scale": 2.0})
    recipe = recipe.model_copy(update={"layers": [recipe.layers[0], fast]})
    stack = Stack(recipe, OBS, ACT)
    assert stack.layers[1].action_space == Box(-4.0, 4.0, (1,), np.float32)
    gate = make([4, 1], "gate")
    assert gate.layers[0].action_space == Box(np.array([-2, -1], np.float32), np.array([2, 1], np.float32))


@pytest.mark.parametrize(("kinds", "ranges"), [
    (["residual-clip", "gate", "residual-clip"], [(0, 4), (-2, 2), (-2, 2)]),  # below a residual gate: about zero
    (["gate", "gate", "residual-clip"], [(0, 4), (0, 4), (0, 4)]),  # gates over gates replace the env's action
    (["gate", "residual-clip", "residual-clip"], [(0, 4), (0, 4), (-2, 2)]),
])
def test_a_layer_in_place_of_a_residual_gate_has_its_range_centred_on_zero(kinds, ranges):
    """On an action range off zero ([0, 4]): a layer whose output stands in for a residual (below a gate that is
    itself a residual) adds to the layers above it as the gate's own action would, so its range is centred on
    zero too; one whose output stands in for the environment's action is not."""
    stack = Stack(stack_recipe([4, 2, 1], kinds), OBS, Box(0.0, 4.0, (1,), np.float32))
    assert [(float(layer.action_space.low[0]), float(layer.action_space.high[0])) for layer in stack.layers] == ranges


def test_observation_is_obs_plus_held_actions_of_the_named_slower_layers():
    stack = make([4, 2, 1], ["gate", "residual-clip", "residual-clip"])
    stack.hold(0, np.array([1.5, 1.0]))
    stack.hold(1, np.array([-0.5]))
    obs = np.array([0.1, 0.2, 0.3])
    assert stack.observation(2, obs) == pytest.approx([0.1, 0.2, 0.3, 1.5, -0.5])  # no gate dimension
    assert stack.observation_spaces[2].shape == (5,)
    assert stack.observation(0, obs) == pytest.approx(obs)


def test_rewards_action_penalty_is_mean_abs_action_over_the_layers_bound():
    recipe = stack_recipe([4, 1])
    fast = recipe.layers[1].model_copy(update={"action_scale": 2.0, "action_penalty": 1.0})
    stack = Stack(recipe.model_copy(update={"layers": [recipe.layers[0], fast]}), OBS, ACT)
    stack.hold(0, np.array([1.0]))
    stack.hold(1, np.array([-1.0]))
    rewards = stack.layer_rewards(-3.0, stack.compose())
    assert rewards == pytest.approx({0: -3.0, 1: -3.0 - 1.0 / 4.0})  # |a| / (2 x max action 2)


@pytest.mark.parametrize(("delay", "paid_from", "paid"), [
    (1, "landing", [0.0, 0.5, 1.5]), (1, "decision", [0.5, 1.5, 1.0]),
    (2, "landing", [0.0, 0.0, 0.5]), (2, "decision", [0.5, 1.5, 1.0]),  # (the newest in flight, not the oldest)
])
def test_a_delayed_action_penalty_is_paid_while_the_output_acts_or_from_its_decision(delay, paid_from, paid):
    """Fast outputs 0.5, 1.5, 1.0 at steps 0-2, each landing `delay` steps later: by default step t pays for the
    output acting (none before the first lands), with `action_penalty_from = "decision"` for the one chosen at t."""
    recipe = stack_recipe([2, 1])
    slow = recipe.layers[0].model_copy(update={"delay": 1})
    fast = recipe.layers[1].model_copy(update={"delay": delay, "action_scale": 2.0, "action_penalty": 1.0,
                                               "action_penalty_from": paid_from})
    stack = Stack(recipe.model_copy(update={"layers": [slow, fast]}), OBS, ACT)
    shares = []
    for output in (0.5, 1.5, 1.0):
        for i in (0, 1) if stack.rules.due(0)[0] else (1,):
            stack.decide(i, stack.observation(i, np.zeros(3, np.float32)), np.array([output if i else 0.0]))
        shares.append(stack.layer_rewards(-3.0, stack.compose()))
        stack.tick()
    assert [s[1] for s in shares] == pytest.approx([-3.0 - p / 4.0 for p in paid])  # |a| / (2 x max action 2)
    assert [s[0] for s in shares] == pytest.approx([-3.0] * 3)


@pytest.mark.parametrize(("env", "per_step"), [("Pendulum-v1", 1550 / 200), ("dmc:cartpole-balance", 1000 / 1000),
                                               ("InvertedDoublePendulum-v5", 9400 / 1000)])
def test_an_action_penalty_per_step_of_reward_range_scales_with_the_task(env, per_step):
    recipe = stack_recipe([4, 1], env=env)
    fast = recipe.layers[1].model_copy(update={"action_scale": 2.0, "action_penalty": 0.1,
                                               "action_penalty_unit": "reward-per-step"})
    space = Box(-1.0, 1.0, (1,), np.float32)
    stack = Stack(recipe.model_copy(update={"layers": [recipe.layers[0], fast]}), OBS, space)
    stack.hold(0, np.array([0.5]))
    stack.hold(1, np.array([-1.0]))
    rewards = stack.layer_rewards(0.5, stack.compose())
    assert rewards[1] == pytest.approx(0.5 - 0.1 * per_step * 1.0 / 2.0)  # |a| / (2 x max action 1)


@pytest.mark.parametrize(("reward", "expected"), [(-3.0, -6.0), (0.0, 0.0), (2.0, 1.0)])
def test_rewards_of_a_deferring_gate_are_scaled(reward, expected):
    stack = make([4, 1], "gate")
    stack.hold(0, np.array([1.0, -1.0]))
    stack.hold(1, np.array([0.2]))
    assert stack.layer_rewards(reward, stack.compose()) == pytest.approx({0: expected, 1: reward})
    stack.hold(0, np.array([1.0, 1.0]))  # committed: plain reward for both
    assert stack.layer_rewards(reward, stack.compose()) == pytest.approx({0: reward, 1: reward})


def test_active_must_name_layers():
    with pytest.raises(ValueError, match="non-empty subset"):
        make([2, 1], active=["nope"])


def delayed(periods, delay, kinds="residual-clip"):
    recipe = stack_recipe(periods, kinds)
    layers = [layer.model_copy(update={"delay": delay}) for layer in recipe.layers]
    return Stack(recipe.model_copy(update={"layers": layers}), OBS, ACT)


def test_a_delayed_layers_action_takes_effect_one_decision_later():
    stack = delayed([1], 1)
    stack.hold(0, np.array([0.5]))
    assert stack.compose().action == pytest.approx([0.0])  # the initial in-flight action
    assert stack.observation(0, np.zeros(3)) == pytest.approx([0, 0, 0, 0.5])  # sees what is in flight
    stack.tick()
    stack.hold(0, np.array([-1.0]))
    assert stack.compose().action == pytest.approx([0.5])
    assert stack.observation(0, np.zeros(3))[-1] == pytest.approx(-1.0)
    assert stack.observation_spaces[0].shape == (4,)


def test_each_layers_delay_is_its_own_period_so_slow_actions_land_later():
    stack = delayed([2, 1], 1)
    executed = []
    for t in range(5):  # the slow layer chooses 1.0 at t=0 and 0.5 at t=2; the fast 0.1 every step
        if t % 2 == 0:
            stack.hold(0, np.array([1.0 if t == 0 else 0.5]))
        stack.hold(1, np.array([0.1]))
        executed.append(float(stack.compose().action[0]))
        stack.tick()
    # fast lands one step later (t >= 1), slow one slow period later (1.0 from t=2, 0.5 from t=4)
    assert executed == pytest.approx([0.0, 0.1, 1.1, 1.1, 0.6])


def test_a_delay_of_two_decisions_queues_in_order():
    stack = delayed([1], 2)
    seen = []
    for a in (0.1, 0.2, 0.3, 0.4):
        stack.hold(0, np.array([a]))
        seen.append(float(stack.compose().action[0]))
    assert seen == pytest.approx([0.0, 0.0, 0.1, 0.2])
    assert stack.observation(0, np.zeros(3))[3:] == pytest.approx([0.3, 0.4])
    stack.reset()
    assert stack.observation(0, np.zeros(3))[3:] == pytest.approx([0.0, 0.0])


def test_a_repeating_layer_holds_its_output_for_the_chosen_number_of_periods():
    recipe = stack_recipe([2, 1])
    slow = recipe.layers[0].model_copy(update={"max_repeat": 3})
    stack = Stack(recipe.model_copy(update={"layers": [slow, recipe.layers[1]]}), OBS, ACT)
    assert stack.layers[0].action_space == Box(np.array([-2, 1], np.float32), np.array([2, 3], np.float32))
    schedule = []
    for t in range(10):
        decided = decisions_at(stack, [np.array([0.5, 2.6 if t == 0 else 1.2]), np.array([0.1])])
        schedule.append(decided)
        stack.tick()
    # 2.6 rounds to 3 periods of 2 steps: the slow layer decides again at t=6, then every period
    assert [0 in d for d in schedule] == [True, False, False, False, False, False, True, False, True, False]
    assert stack.compose().action == pytest.approx([0.6])  # the count is not part of the action


def test_joint_gate_shaping_defer_and_deviation_penalties():
    recipe = stack_recipe([4, 1], "gate")
    slow = recipe.layers[0].model_copy(update={"defer_reward_scale": (1.0, 1.0), "defer_penalty": 1.0,
                                               "deviation_penalty": 0.5})
    fast = recipe.layers[1].model_copy(update={"deviation_penalty": 2.0, "action_scale": 0.5})  # its range: [-1, 1]
    stack = Stack(recipe.model_copy(update={"layers": [slow, fast]}), OBS, ACT)
    stack.hold(0, np.array([1.0, -1.0]))  # proposes 1.0 but defers
    stack.hold(1, np.array([-1.0]))  # executed -1.0: deviation |(-1) - 1| / the env's max action 2 = 1.0
    rewards = stack.layer_rewards(-3.0, stack.compose())
    assert rewards == pytest.approx({0: -3.0 - 1.0 - 0.5 * 1.0, 1: -3.0 - 2.0 * 1.0})
    stack.hold(0, np.array([1.0, 1.0]))  # commits: no penalties for anyone
    assert stack.layer_rewards(-3.0, stack.compose()) == pytest.approx({0: -3.0, 1: -3.0})


def test_below_a_committed_gate_no_deviation_is_paid_though_a_gate_above_it_defers():
    """Gate 8 defers (proposing 1.0), gate 4 below it commits to 0.0, which is executed: the slow gate pays its defer
    penalty and its deviation 0.5 x |0 - 1| / 2; the fast layer, kept out by the committed gate, pays nothing."""
    recipe = stack_recipe([8, 4, 1], ["gate", "gate", "residual-clip"])
    slow = recipe.layers[0].model_copy(update={"defer_reward_scale": (1.0, 1.0), "defer_penalty": 1.0,
                                               "deviation_penalty": 0.5})
    fast = recipe.layers[2].model_copy(update={"deviation_penalty": 2.0})
    stack = Stack(recipe.model_copy(update={"layers": [slow, recipe.layers[1], fast]}), OBS, ACT)
    stack.hold(0, np.array([1.0, -1.0]))  # proposes 1.0, defers
    stack.hold(1, np.array([0.0, 1.0]))  # commits to 0.0
    stack.hold(2, np.array([-1.0]))  # not reached
    composition = stack.compose()
    assert composition.action == pytest.approx([0.0])
    assert stack.layer_rewards(-3.0, composition) == pytest.approx({0: -3.0 - 1.0 - 0.25, 1: -3.0, 2: -3.0})


def learning_from_commits(periods, kinds, **kw):
    recipe = stack_recipe(periods, kinds)
    layers = [*recipe.layers[:-1], recipe.layers[-1].model_copy(update={"learn_from_commits": True})]
    return Stack(recipe.model_copy(update={"layers": layers}), OBS, ACT, **kw)


def test_a_layer_that_learns_from_commits_decides_under_a_commit_and_records_the_executed_action():
    stack = learning_from_commits([3, 1], "gate")
    commit, defer, fast = np.array([1.5, 0.5]), np.array([1.5, -0.5]), np.array([0.3], np.float32)
    seen = np.zeros(4, np.float32)
    timeline = []
    for t in range(6):  # the slow layer commits 1.5 at t = 0 and defers at t = 3
        due = stack.next_due(0)
        if due == 0:
            stack.decide(0, seen, commit if t == 0 else defer)
            due = stack.next_due(1)
        stack.decide(due, seen, fast)
        recorded, executed = stack.decisions[1].output[0], stack.compose().action[0]
        timeline.append((t, due, round(float(recorded), 6), round(float(executed), 6)))
        stack.tick()
    assert timeline == [
        (0, 1, 1.5, 1.5), (1, 1, 1.5, 1.5), (2, 1, 1.5, 1.5),  # committed: the fast layer records 1.5
        (3, 1, 0.3, 0.3), (4, 1, 0.3, 0.3), (5, 1, 0.3, 0.3),  # deferred: its own output, executed
    ]


def test_at_evaluation_a_layer_that_learns_from_commits_is_not_asked_under_a_commit():
    stack = learning_from_commits([3, 1], "gate", evaluation=True)
    stack.decide(0, np.zeros(4, np.float32), np.array([1.5, 0.5]))
    assert stack.next_due(1) is None
    stack.tick()
    assert stack.next_due(0) is None


def test_under_a_commit_what_the_layers_above_the_gate_add_is_not_part_of_the_recorded_action():
    stack = learning_from_commits([4, 2, 1], ["residual-clip", "gate", "residual-clip"])
    seen = np.zeros(5, np.float32)
    stack.decide(0, seen, np.array([1.0]))
    stack.decide(1, seen, np.array([0.5, 1.0]))  # commits 0.5: executed 1.0 + 0.5 = 1.5
    assert stack.next_due(2) == 2
    stack.decide(2, seen, np.array([-0.7]))
    assert stack.decisions[2].output == pytest.approx([0.5]) and stack.compose().action == pytest.approx([1.5])
