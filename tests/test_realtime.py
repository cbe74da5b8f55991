"""The real-time (delayed) setting, traced by hand: at every decision, what each layer sees of the
slower layers and of its own outputs in flight, and what the environment executes."""

import numpy as np
import pytest
from gymnasium.spaces import Box

from layered import load_recipe
from layered.stack import Stack

OBS = Box(-1.0, 1.0, (1,), np.float32)
ACT = Box(-2.0, 2.0, (1,), np.float32)
# Each decision outputs its own label's value, so a value seen names the decision it came from:
# slow decision k outputs S[k], mid decision k outputs M[k], the fast decision at step t F[t].
S = [0.5, 0.6, 0.7, 0.8]
M = [0.05, 0.06, 0.07, 0.08, 0.09]
F = [0.001 * (t + 1) for t in range(12)]
VALUE = {f"{name}{k}": v for name, values in (("S", S), ("M", M), ("F", F)) for k, v in enumerate(values)}
VALUE["0"] = 0.0


def realtime_stack(periods, delays, evaluation=False, threshold=None, in_flight=False, executed=False) -> Stack:
    names = [f"l{k}" for k in range(len(periods))]
    layers = [{"name": n, "period": p, "delay": d, "sees": ["obs", *names[:k]]}
              for k, (n, p, d) in enumerate(zip(names, periods, delays, strict=True))]
    for layer in layers[1:] if in_flight else []:
        layer["sees_in_flight"] = layer["delay"] > 0
    for layer in layers if executed else []:
        layer["sees_executed"] = True
    recipe = load_recipe({"env": {"id": "Pendulum-v1"}, "layers": layers})
    return Stack(recipe, OBS, ACT, evaluation=evaluation, threshold=threshold)


def play(stack: Stack, steps: int, outputs=None):
    """Step the stack, each layer deciding its scripted outputs in turn; per decision (step, layer,
    what it saw of the slower layers, what it saw in flight), and the executed action per step."""
    counters = [0] * len(stack.layers)
    series = outputs or ([S, F] if len(stack.layers) == 2 else [S, M, F])
    seen, executed = [], []
    for t in range(steps):
        i = stack.next_due(0)
        while i is not None:
            obs = stack.observation(i, np.zeros(1, np.float32))
            slower, inflight = obs[1:1 + i].tolist(), obs[1 + i:].tolist()
            seen.append((t, i, slower, inflight))
            stack.decide(i, obs, np.array([series[i][counters[i]]], np.float32))
            counters[i] += 1
            i = stack.next_due(i + 1)
        executed.append(float(stack.compose().action[0]))
        stack.tick()
    return seen, executed


def values(*labels):
    return [pytest.approx(VALUE[label]) for label in labels]


def sums(*rows):
    return [pytest.approx(sum(VALUE[label] for label in row.split("+"))) for row in rows]


def assert_views_are_what_acts(stack: Stack, periods, seed: int, views_of) -> None:
    """Play random outputs for 40 steps; at each decision of layer i, `views_of(t, i, obs)` names what it saw of
    the slower layers for some later steps, as (step, values): each must be their outputs in effect at that step."""
    rng = np.random.default_rng(seed)
    series = [list(rng.uniform(-0.5, 0.5, 64)) for _ in periods]
    counters, views, held = [0] * len(periods), [], []
    for t in range(40):
        i = stack.next_due(0)
        while i is not None:
            obs = stack.observation(i, np.zeros(1, np.float32))
            views += [(step, i, view) for step, view in views_of(t, i, obs)]
            stack.decide(i, obs, np.array([series[i][counters[i]]], np.float32))
            counters[i] += 1
            i = stack.next_due(i + 1)
        held.append([float(h[0]) for h in stack.held])
        stack.tick()
    checked = [(step, i, view) for step, i, view in views if step < 40]
    assert len(checked) > 30
    for step, i, view in checked:
        assert view == pytest.approx(held[step][:i]), (step, i)


def test_periods_2_1_each_output_landing_one_of_its_own_periods_later():
    """The paper's setting: slow output chosen at 2k acts at 2k+2 and 2k+3; fast output chosen at t acts at t+1."""
    seen, executed = play(realtime_stack([2, 1], [1, 1]), 7)
    fast = [(t, slower, inflight) for t, i, slower, inflight in seen if i == 1]
    # at step t the fast layer sees the slow output that will act at t+1, when its own output acts
    assert [s for _, s, _ in fast] == [values(x) for x in ("0", "S0", "S0", "S1", "S1", "S2", "S2")]
    assert [f for _, _, f in fast] == [values(x) for x in ("0", "F0", "F1", "F2", "F3", "F4", "F5")]
    slow = [(t, inflight) for t, i, _, inflight in seen if i == 0]
    assert slow == [(0, values("0")), (2, values("S0")), (4, values("S1")), (6, values("S2"))]
    assert executed == sums("0", "F0", "S0+F1", "S0+F2", "S1+F3", "S1+F4", "S2+F5")


def test_periods_4_1_with_a_delay_of_one_decision_each():
    seen, executed = play(realtime_stack([4, 1], [1, 1]), 9)
    fast = [slower for _, i, slower, _ in seen if i == 1]
    assert fast == [values(x) for x in ("0", "0", "0", "S0", "S0", "S0", "S0", "S1", "S1")]
    assert executed == sums("0", "F0", "F1", "F2", "S0+F3", "S0+F4", "S0+F5", "S0+F6", "S1+F7")


def test_three_layers_4_2_1_each_delayed_one_decision():
    seen, executed = play(realtime_stack([4, 2, 1], [1, 1, 1]), 9)
    mid = [(t, slower) for t, i, slower, _ in seen if i == 1]
    assert mid == [(0, values("0")), (2, values("S0")), (4, values("S0")), (6, values("S1")), (8, values("S1"))]
    fast = [slower for _, i, slower, _ in seen if i == 2]  # (slow, mid) in effect one step later
    assert fast == [values(*x) for x in (("0", "0"), ("0", "M0"), ("0", "M0"), ("S0", "M1"), ("S0", "M1"),
                                         ("S0", "M2"), ("S0", "M2"), ("S1", "M3"), ("S1", "M3"))]
    assert executed == sums("0", "F0", "M0+F1", "M0+F2", "S0+M1+F3", "S0+M1+F4", "S0+M2+F5", "S0+M2+F6",
                            "S1+M3+F7")


@pytest.mark.parametrize(("periods", "delays"), [
    ([2, 1], [1, 1]), ([4, 1], [1, 1]), ([4, 2, 1], [1, 1, 1]), ([4, 1], [2, 1]), ([4, 1], [1, 3]),
    ([8, 2, 1], [1, 2, 1]), ([4, 1], [0, 0]),
], ids=str)
def test_every_layer_sees_the_slower_outputs_its_own_output_is_added_to(periods, delays):
    """Whenever the slower layers' outputs land no sooner than the observer's, what a layer sees of
    them at a decision is exactly what acts beside its output when that output lands."""
    assert_views_are_what_acts(realtime_stack(periods, delays), periods, 0,
                               lambda t, i, obs: [(t + delays[i] * periods[i], obs[1:1 + i].tolist())])


def test_sees_in_flight_shows_the_slow_output_acting_beside_the_fast_one_in_flight():
    """The paper's setting again: at odd steps the slow output acting now (beside the fast output in flight)
    is not the one the fast layer's new output will be added to; `sees_in_flight` shows both."""
    seen, executed = play(realtime_stack([2, 1], [1, 1], in_flight=True), 7)
    fast = [slower + inflight for _, i, slower, inflight in seen if i == 1]  # S in effect at t + 1, F_t-1, S at t
    assert fast == [values(*x) for x in (("0", "0", "0"), ("S0", "F0", "0"), ("S0", "F1", "S0"), ("S1", "F2", "S0"),
                                         ("S1", "F3", "S1"), ("S2", "F4", "S1"), ("S2", "F5", "S2"))]
    assert executed == sums("0", "F0", "S0+F1", "S0+F2", "S1+F3", "S1+F4", "S2+F5")  # as without it
    assert [f[1] + f[2] for f in fast] == pytest.approx(executed)  # what acts at each step, as the fast layer sees it


@pytest.mark.parametrize(("periods", "delays"), [
    ([2, 1], [1, 1]), ([4, 1], [1, 1]), ([4, 2, 1], [1, 1, 1]), ([4, 1], [1, 3]), ([8, 2, 1], [1, 2, 1]),
], ids=str)
def test_with_sees_in_flight_a_layer_sees_what_acts_beside_each_of_its_outputs_in_flight(periods, delays):
    """Beside each output in flight, the slower layers' outputs in effect when it lands: with its own
    output, everything the environment will execute until its new output lands."""
    def beside_in_flight(t, i, obs):
        flight = obs[1 + i:].reshape(delays[i], 1 + i)  # per output in flight: its own, then what acts beside it
        return [(t + k * periods[i], flight[k, 1:].tolist()) for k in range(delays[i]) if i]

    assert_views_are_what_acts(realtime_stack(periods, delays, in_flight=True), periods, 1, beside_in_flight)


def test_sees_executed_shows_the_slow_layer_the_action_executed_as_its_output_lands():
    """The paper's setting: at its decision the slow layer sees, for its output landing now, the action the
    environment executes now (with the fast correction chosen a step before), as the authors' code shows it."""
    seen, executed = play(realtime_stack([2, 1], [1, 1], executed=True), 7)
    slow = [(t, inflight) for t, i, _, inflight in seen if i == 0]
    assert slow == [(0, values("0")), (2, sums("S0+F1")), (4, sums("S1+F3")), (6, sums("S2+F5"))]
    assert executed == sums("0", "F0", "S0+F1", "S0+F2", "S1+F3", "S1+F4", "S2+F5")  # as without it


@pytest.mark.parametrize("periods", [[2, 1], [4, 1], [4, 2, 1], [8, 2, 1]], ids=str)
def test_with_sees_executed_and_a_delay_of_one_every_layer_sees_the_action_executed_at_its_decision(periods):
    """With every layer delayed one decision, the output a layer has in flight at a decision lands at that
    step: it sees the action executed then, whatever the periods."""
    stack = realtime_stack(periods, [1] * len(periods), executed=True)
    seen, executed = play(stack, 12, outputs=[S * 3, F] if len(periods) == 2 else [S * 3, M * 3, F])
    assert len(seen) > 12
    for t, _, _, inflight in seen:
        assert inflight == [pytest.approx(executed[t])], t


@pytest.mark.parametrize(("executed", "bound"), [(False, 4.0), (True, 2.0)])
def test_an_output_in_flight_seen_as_executed_is_bounded_by_the_environments_range(executed, bound):
    """A fast layer of twice the environment's range (2) sees its outputs in flight within its own range, or,
    seen as the executed actions, within the environment's."""
    recipe = load_recipe({"env": {"id": "Pendulum-v1"}, "layers": [
        {"name": "slow", "period": 2, "delay": 1},
        {"name": "fast", "period": 1, "delay": 1, "sees": ["obs", "slow"], "action_scale": 2.0,
         "sees_executed": executed}]})
    low, high = Stack(recipe, OBS, ACT).rules.observation_bounds(1, OBS.low, OBS.high)
    assert (low.tolist(), high.tolist()) == ([-1.0, -2.0, -bound], [1.0, 2.0, bound])  # obs, slow, fast in flight


def test_at_evaluation_an_output_in_flight_shows_what_the_threshold_lets_through():
    # threshold 0.3 x max action 2 = 0.6: a fast correction of 0.1 is dropped when it lands, one of 1.0 is not
    stack = realtime_stack([2, 1], [1, 1], evaluation=True, threshold=0.3)
    seen, executed = play(stack, 4, outputs=[[0.5, 0.5], [0.1, 1.0, 0.1, 1.0]])
    fast_inflight = [inflight for _, i, _, inflight in seen if i == 1]
    assert fast_inflight == [values("0"), [0.0], [pytest.approx(1.0)], [0.0]]
    assert executed == [0.0, 0.0, pytest.approx(1.5), 0.5]
    training = realtime_stack([2, 1], [1, 1])
    seen, _ = play(training, 4, outputs=[[0.5, 0.5], [0.1, 1.0, 0.1, 1.0]])
    assert [inflight for _, i, _, inflight in seen if i == 1][1] == [pytest.approx(0.1)]
