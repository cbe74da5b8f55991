"""The stack's rules over a batch axis: K rows stepped together are K stacks stepped alone, row by row;
hand-traced timelines in which one row resets while the other goes on."""

import numpy as np
import pytest
from conftest import stack_recipe
from gymnasium.spaces import Box

from layered.rules import Rules
from layered.stack import Stack

OBS = Box(-1.0, 1.0, (3,), np.float32)
ACT = Box(-2.0, 2.0, (1,), np.float32)


def rules_of(periods, kinds, rows, **layer_settings):
    """Batched rules for a stack of `periods` and combiners `kinds`, each layer updated with `layer_settings`
    (a list per key, one value per layer), as training runs it."""
    recipe = stack_recipe(periods, kinds)
    layers = [layer.model_copy(update={key: values[k] for key, values in layer_settings.items()})
              for k, layer in enumerate(recipe.layers)]
    stack = Stack(recipe.model_copy(update={"layers": layers}), OBS, ACT)
    return Rules(stack.rules.layers, stack.rules.active, ACT.low, ACT.high, rows)


def output(row, layer, t, episode, size, low, high):
    """A deterministic output of a row's layer at its step t of its episode, within the layer's bounds."""
    rng = np.random.default_rng([row, layer, t, episode])
    return rng.uniform(low, high).astype(np.float32)[:size]


def decide_by_next_due(rules, obs, policy):
    """One stack's decisions of a step as the agent view takes them: from each decision to the next due layer."""
    decided = {i: np.zeros(1, bool) for i in rules.active}
    i, rows = int(rules.next_due(0)[0]), np.ones(1, bool)
    while i >= 0:
        rules.decide(i, policy(i, rules.observation(i, obs), rows), rows)
        decided[i][0] = True
        i = int(rules.next_due(i + 1)[0])
    return decided


@pytest.mark.parametrize(("periods", "kinds", "settings"), [
    ([4, 2, 1], ["gate", "residual-clip", "residual-clip"], {"delay": [0, 1, 1]}),
    ([2, 1], "gate", {"learn_from_commits": [False, True], "deviation_penalty": [1.0, 1.0], "defer_penalty": [0.5, 0]}),
    ([4, 1], "residual-clip", {"delay": [1, 1], "action_penalty": [0.0, 1.0]}),
    ([4, 2, 1], "residual-clip", {"delay": [1, 2, 1], "sees_in_flight": [False, True, True]}),
    ([4, 2, 1], "residual-clip", {"delay": [1, 1, 1], "sees_executed": [True, True, True]}),
    ([2, 1], "residual-clip", {"max_repeat": [3, 1]}),
    ([4, 2, 1], ["gate", "gate", "residual-clip"], {"learn_from_commits": [False, False, True]}),
])
def test_rows_stepped_together_are_the_stacks_stepped_alone(periods, kinds, settings):
    """The batch decides in one pass (`decide_all`); each stack alone walks `next_due` as the agent view does."""
    rows, steps = 5, 40
    lengths = [7, 9, 13, 40, 5]  # each row's episodes end after its own number of steps
    batch = rules_of(periods, kinds, rows, **settings)
    alone = [rules_of(periods, kinds, 1, **settings) for _ in range(rows)]
    episode, rng = [0] * rows, np.random.default_rng(0)
    for _ in range(steps):
        obs = rng.uniform(-1, 1, (rows, 3)).astype(np.float32)

        def act(r, clocks):
            def policy(j, seen, mask):
                picked = np.flatnonzero(mask) if r is None else [r]
                layer = batch.layers[j]
                return np.stack([output(k, j, int(clocks[k if r is None else 0]), episode[k], layer.size, layer.low,
                                        layer.high) for k in picked])
            return policy

        seen_together = {i: batch.observation(i, obs) for i in batch.active}  # before anyone decides
        decided = batch.decide_all(obs, act(None, batch.t))
        together = batch.compose()
        reward = rng.normal(size=rows)
        shares = batch.layer_rewards(reward, together)
        for r, single in enumerate(alone):
            seen = {i: single.observation(i, obs[r:r + 1])[0] for i in single.active}
            decided_alone = decide_by_next_due(single, obs[r:r + 1], act(r, single.t))
            composition = single.compose()
            assert composition.action[0].tolist() == together.action[r].tolist()
            for i in single.active:
                assert bool(decided_alone[i][0]) == bool(decided[i][r])
                assert composition.routes[i][0] == together.routes[i][r]
                assert composition.contributions[i][0].tolist() == together.contributions[i][r].tolist()
                assert single.layer_rewards(reward[r:r + 1], composition)[i][0] == shares[i][r]
                assert single.held[i][0].tolist() == batch.held[i][r].tolist()
                assert seen[i].tolist() == seen_together[i][r].tolist()
        ended = np.array([batch.t[k] + 1 >= lengths[k] for k in range(rows)])
        batch.tick()
        batch.reset(ended)
        for r in np.flatnonzero(ended):
            alone[r].tick()
            alone[r].reset()
            episode[r] += 1
        for r in np.flatnonzero(~ended):
            alone[r].tick()


def play(rules, obs, outputs, steps, resets):
    """Step `rules`, layer i of row k deciding outputs[i][k](t) at its row's step t; rows reset before the
    global steps listed in `resets` (step: mask). Per global step: the decided masks, the executed
    actions, and the fastest layer's observation in each row before it decides."""
    trace = []
    for g in range(steps):
        if g in resets:
            rules.reset(np.array(resets[g]))
        fast = len(rules.layers) - 1
        seen = rules.observation(fast, obs)
        decided = rules.decide_all(obs, lambda i, _, mask: np.array(
            [outputs[i][k](int(rules.t[k])) for k in np.flatnonzero(mask)], np.float32))
        action = rules.compose().action
        trace.append(({i: m.tolist() for i, m in decided.items()}, action[:, 0].astype(float).round(6).tolist(), seen))
        rules.tick()
    return trace


def test_a_residual_pair_in_which_one_row_starts_a_new_episode():
    """slow (period 2) + fast (period 1), residual-clip. Row 0 holds slow 1.0, row 1 slow -1.0; the fast
    layer outputs 0.1 x its row's step. Row 0 ends its episode after 3 steps, row 1 goes on."""
    rules = rules_of([2, 1], "residual-clip", rows=2)
    outputs = [[lambda t: [1.0], lambda t: [-1.0]], [lambda t: [0.1 * t], lambda t: [0.1 * t]]]
    trace = play(rules, np.zeros((2, 3), np.float32), outputs, 5, {3: [True, False]})
    # row 0: steps 0 1 2 | 0 1 (reset);  row 1: steps 0 1 2 3 4
    assert [d[0] for d, _, _ in trace] == [[True, True], [False, False], [True, True], [True, False], [False, True]]
    assert [d[1] for d, _, _ in trace] == [[True, True]] * 5
    assert [a for _, a, _ in trace] == [[1.0, -1.0], [1.1, -0.9], [1.2, -0.8], [1.0, -0.7], [1.1, -0.6]]
    # the fast layer sees the observation and the slow layer's output in effect (zero before its first)
    assert trace[3][2][:, 3].tolist() == [0.0, -1.0]


def test_a_gate_over_a_delayed_fast_layer_with_a_reset_in_one_row():
    """slow (period 2, gate) over fast (period 1, a delay of one decision). Row 0's gate commits to 0.5,
    row 1's defers; the fast layer outputs 0.1 x (its row's step + 1). Row 1 restarts before step 2."""
    rules = rules_of([2, 1], "gate", rows=2, delay=[0, 1])
    outputs = [[lambda t: [0.5, 1.0], lambda t: [0.5, -1.0]], [lambda t: [0.1 * (t + 1)]] * 2]
    trace = play(rules, np.zeros((2, 3), np.float32), outputs, 4, {2: [False, True]})
    slow, fast = [d[0] for d, _, _ in trace], [d[1] for d, _, _ in trace]
    assert slow == [[True, True], [False, False], [True, True], [False, False]]
    assert fast == [[False, True]] * 4  # never under row 0's committed gate
    # row 0: the committed 0.5; row 1: the fast output of the step before lands (zero after the reset)
    assert [a for _, a, _ in trace] == [[0.5, 0.0], [0.5, 0.1], [0.5, 0.0], [0.5, 0.1]]
    # row 1's fast layer sees its output in flight as it will be executed: 0.1 at step 1, cleared by the reset
    assert [float(s[1, -1]) for _, _, s in trace] == pytest.approx([0.0, 0.1, 0.0, 0.1])


def test_a_repeat_count_is_rounded_and_held_within_one_and_the_maximum():
    from layered.rules import Layer

    def layer(max_repeat):
        return Layer("x", 2, np.array([-1, -1, 1], np.float32), np.array([1, 1, max_repeat], np.float32),
                     max_repeat=max_repeat)

    outputs = np.array([[0.0, 9.0, 0.2], [0.0, 9.0, 1.6], [0.0, 9.0, 2.4], [0.0, 9.0, 7.0]], np.float32)
    assert layer(1).repeats(outputs) == 1
    assert list(layer(2).repeats(outputs)) == [1, 2, 2, 2]
    assert list(layer(3).repeats(outputs)) == [1, 2, 2, 3]


@pytest.mark.parametrize("active", [[], [1, 0], [0, 2], [0, 0]])
def test_the_present_layers_must_be_increasing_indices_of_the_stack(active):
    layers = rules_of([2, 1], "residual-clip", 1).layers
    with pytest.raises(ValueError, match="must be increasing indices of the 2 layers"):
        Rules(layers, active, ACT.low, ACT.high)


def test_what_a_layer_sees_is_bounded_to_include_zero():
    """Before the first decision an output is zero, so the bounds of a seen output, and of outputs in
    flight, include 0 even when the layer's own bounds do not."""
    from layered.rules import Layer

    slow = Layer("slow", 2, np.array([0.25], np.float32), np.array([0.5], np.float32))
    fast = Layer("fast", 1, np.array([0.5], np.float32), np.array([0.75], np.float32), sees=(0,), delay=1)
    rules = Rules([slow, fast], [0, 1], ACT.low, ACT.high)
    low, high = rules.observation_bounds(1, OBS.low, OBS.high)
    assert low.tolist() == [-1, -1, -1, 0.0, 0.0] and high.tolist() == [1, 1, 1, 0.5, 0.75]
    negative = Layer("fast", 1, np.array([-2.0], np.float32), np.array([-1.5], np.float32), sees=(0,), delay=1)
    low, high = Rules([slow, negative], [0, 1], ACT.low, ACT.high).observation_bounds(1, OBS.low, OBS.high)
    assert low.tolist()[-1] == -2.0 and high.tolist()[-1] == 0.0


def test_the_upcoming_decision_step_rounds_up_to_the_period():
    rules = rules_of([4, 1], "residual-clip", 3)
    rules.t[:] = [0, 5, 8]
    assert rules.upcoming(0).tolist() == [0, 8, 8] and rules.upcoming(1).tolist() == [0, 5, 8]


def test_a_gate_that_is_the_fastest_present_layer_only_adds():
    """In a phase where the gate layer is present alone, there is no layer below to defer to: its
    action is executed whatever its gate says."""
    rules = rules_of([4, 1], "gate", 2)
    alone = Rules(rules.layers, [0], ACT.low, ACT.high, 2)
    alone.hold(0, np.array([[0.5, -1.0], [-0.25, 1.0]], np.float32))  # a deferring gate, a committing one
    composition = alone.compose()
    assert composition.action[:, 0].tolist() == [0.5, -0.25]
    assert composition.routes[0].tolist() == [0, 0]


def test_next_due_by_default_starts_at_the_slowest_layer_and_says_minus_one_for_none():
    rules = rules_of([4, 1], "residual-clip", 2)
    assert rules.next_due().tolist() == [0, 0]
    rules.t[:] = [1, 4]
    assert rules.next_due(np.array([0, 1])).tolist() == [1, 1]  # a start per row
    assert rules.next_due(np.array([2, 0])).tolist() == [-1, 0]


def test_a_row_whose_layer_is_due_is_not_reopened_by_a_commit_in_another_row():
    rules = rules_of([2, 1], "gate", 2)
    rules.hold(0, np.array([[0.5, -1.0], [0.5, 1.0]], np.float32))  # row 1's gate commits
    rules.t[:] = [2, 3]  # the gate is due in row 0 only
    assert rules.next_due(0).tolist() == [0, -1]


def test_below_a_committed_gate_only_a_layer_learning_from_commits_is_due():
    rules = rules_of([2, 1, 1], ["gate", "residual-clip"], 2, learn_from_commits=[False, True, False])
    rules.hold(0, np.array([[0.5, 1.0], [0.5, -1.0]], np.float32))  # row 0 commits, row 1 defers
    assert rules.next_due(1).tolist() == [1, 1]
    assert rules.next_due(2).tolist() == [-1, 2]


def test_outputs_two_decisions_in_flight_take_effect_in_turn():
    """A delay of 2 decisions at period 2: what is in effect at each coming step, and what the layer
    sees of its own outputs in flight."""
    rules = rules_of([2, 1], "residual-clip", 1, delay=[0, 2])
    fast = 1
    for value in (0.1, 0.2, 0.3):  # the fast layer decides every step
        rules.hold(fast, np.array([[value]], np.float32))
        rules.tick()
    # decided 0.1, 0.2, 0.3 at steps 0, 1, 2: 0.1 took effect at 2; 0.2 and 0.3 are in flight
    assert rules.held[fast].tolist() == [[pytest.approx(0.1)]]
    steps = rules.t.copy()  # now, step 3
    assert rules.in_effect(fast, steps)[0].tolist() == [pytest.approx(0.2)]
    assert rules.in_effect(fast, steps + 1)[0].tolist() == [pytest.approx(0.3)]
    seen = rules.observation(fast, np.zeros((1, 3), np.float32))[0]
    assert seen[-2:].tolist() == [pytest.approx(0.2), pytest.approx(0.3)]  # its own outputs in flight, in turn


def test_decided_records_what_each_row_decided_and_tick_advances_only_the_masked_rows():
    rules = rules_of([2, 1], "residual-clip", 3)
    rules.decide(1, np.array([[0.5], [0.25], [-0.5]], np.float32))
    rules.decide(1, np.array([[1.0], [1.0], [1.0]], np.float32), np.array([False, True, False]))
    assert rules.decided[1][:, 0].tolist() == [0.5, 1.0, -0.5]
    rules.tick(np.array([True, False, True]))
    assert rules.t.tolist() == [1, 0, 1]


def test_decide_all_hands_each_layer_its_own_observation():
    rules = rules_of([2, 1], "residual-clip", 2)  # the fast layer sees the slow layer's output
    obs = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], np.float32)
    seen = {}

    def act(i, observation, rows):
        seen[i] = observation.copy()
        return np.full((int(rows.sum()), rules.layers[i].size), 0.5 if i == 0 else 0.0, np.float32)

    rules.decide_all(obs, act)
    assert seen[0].tolist() == obs.tolist()
    assert seen[1][:, :3].tolist() == obs.tolist() and seen[1][:, 3].tolist() == [0.5, 0.5]


def test_deferring_scales_rewards_up_to_zero_and_down_above_and_penalises_deviation():
    rules = rules_of([2, 1], "gate", 2, defer_reward_scale=[(2.0, 0.5), (1.0, 1.0)],
                     deviation_penalty=[0.0, 1.0], action_penalty=[0.0, 1.0])
    rules.hold(0, np.array([[1.0, -1.0], [1.0, -1.0]], np.float32))  # both rows defer, proposing 1.0
    rules.hold(1, np.array([[0.0], [-1.0]], np.float32))  # the executed actions: 0.0 and -1.0
    composition = rules.compose()
    shares = rules.layer_rewards(np.array([0.5, -0.5]), composition)
    assert shares[0].tolist() == [0.25, -1.0]
    # fast: the action penalty (|a| / fast half-range 2) and the deviation from the proposed 1.0 (/ half-range 2)
    # (a deferring gate's own action is not executed: the actions are the fast layer's 0.0 and -1.0)
    assert shares[1].tolist() == [pytest.approx(0.5 - 0.0 - 0.5), pytest.approx(-0.5 - 0.5 - 1.0)]


def test_rules_restored_from_their_state_step_on_as_the_rules_they_were_taken_from():
    """A 3-layer stack with delays, a gate and repeats, two rows out of step: its state taken mid-episode
    and put into new rules, both go on identically; the state is a copy, not a view."""
    settings = {"delay": [1, 0, 1], "max_repeat": [1, 3, 1]}
    rules = rules_of([4, 2, 1], ["gate", "residual-clip", "residual-clip"], 2, **settings)
    outputs = [[lambda t, k=k, i=i: output(k, i, t, 0, rules.layers[i].size, rules.layers[i].low, rules.layers[i].high)
                for k in range(2)] for i in range(3)]
    outputs[1][0] = lambda t: rules.layers[1].high  # row 0's middle layer repeats its decisions three times
    obs = np.zeros((2, 3), np.float32)
    play(rules, obs, outputs, 7, {3: [True, False]})
    state = rules.state_dict()
    restored = rules_of([4, 2, 1], ["gate", "residual-clip", "residual-clip"], 2, **settings)
    restored.load_state_dict(state)
    ahead = play(rules, obs, outputs, 9, {4: [False, True]})
    assert int(state["t"][0]) == 4 and rules.t[0] != 4  # taken before the steps above
    behind = play(restored, obs, outputs, 9, {4: [False, True]})
    for (d1, a1, s1), (d2, a2, s2) in zip(ahead, behind, strict=True):
        assert d1 == d2 and a1 == a2 and np.array_equal(s1, s2)
