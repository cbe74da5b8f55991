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
