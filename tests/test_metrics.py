"""Metric formulas against values computed by hand."""

import numpy as np
import pytest

from layered.metrics import (
    Evaluation,
    EpisodeMeter,
    StepRecord,
    at_bounds,
    best_evaluation,
    held,
    measure_episode,
    normalised_auc,
    summarise,
)


def a(*xs):
    return np.array(xs, np.float32)


UNBOUNDED = (a(-np.inf), a(np.inf))  # no action is at these bounds


def played(actions, bounds=UNBOUNDED):
    """The measures of an episode of these executed actions (no layer named, rewards 0) in an action space of
    these `bounds`."""
    return measure_episode([StepRecord(action, 0.0, (), {}) for action in actions], {}, bounds)


def test_action_repetition_counts_exact_repeats_over_all_steps():
    actions = [a(1.0), a(1.0), a(1.0), a(0.5), a(0.5)]  # steps 2, 3 and 5 repeat
    assert played(actions).repetition == pytest.approx(3 / 5)
    assert played([a(1.0, 2.0), a(1.0, 2.0001)]).repetition == 0.0
    assert played([]).repetition == 0.0


def test_repetition_at_the_bounds_counts_the_repeats_whose_action_is_at_a_bound_in_every_dimension():
    # in [-1, 1]: steps 2 and 3 repeat +1 and step 7 repeats -1 (at the bounds); step 5 repeats 0.5 (held)
    actions = [a(1.0), a(1.0), a(1.0), a(0.5), a(0.5), a(-1.0), a(-1.0)]
    m = played(actions, (a(-1.0), a(1.0)))
    assert (m.repetition, m.repetition_at_bounds) == (pytest.approx(4 / 7), pytest.approx(3 / 7))
    assert played(actions).repetition_at_bounds == 0.0, "no bound reached"
    # two dimensions with bounds of their own, (-2, 2) and (-1, 1): a repeat counts only with both at a bound
    bounds = (a(-2.0, -1.0), a(2.0, 1.0))
    assert at_bounds(np.array([[2.0, -1.0], [2.0, 0.3], [1.0, 1.0], [-2.0, 1.0]]), bounds).tolist() == [
        True, False, False, True]
    m = played([a(2.0, -1.0), a(2.0, -1.0), a(2.0, 0.3), a(2.0, 0.3), a(-2.0, 1.0)], bounds)
    assert (m.repetition, m.repetition_at_bounds) == (pytest.approx(2 / 5), pytest.approx(1 / 5))
    # a first step at a bound repeats nothing; an action past a bound (not clipped) counts as at it
    assert played([a(1.0)], (a(-1.0), a(1.0))).repetition_at_bounds == 0.0
    assert played([a(1.5), a(1.5)], (a(-1.0), a(1.0))).repetition_at_bounds == 0.5


def test_normalised_auc_is_the_trapezoid_over_range_and_span():
    # returns -1550, -775, 0 over Pendulum's (-1550, 0): normalised 0, 0.5, 1 at steps 0, 10, 30
    # area = 10 * (0 + 0.5) / 2 + 20 * (0.5 + 1) / 2 = 2.5 + 15 = 17.5; span 30
    assert normalised_auc([0, 10, 30], [-1550, -775, 0], (-1550, 0)) == pytest.approx(17.5 / 30)
    assert normalised_auc([0, 5000], [1000, 1000], (0, 1000)) == pytest.approx(1.0)
    assert normalised_auc([7], [50], (0, 100)) == pytest.approx(0.5)


def test_the_best_evaluation_is_the_highest_and_the_earliest_of_equals():
    assert best_evaluation([-900.0, -150.5, -151.0, -150.5]) == 1  # index 3 ties it, later
    assert best_evaluation([5.0]) == 0
    assert best_evaluation([1.0, 2.0, 3.0]) == 2


def test_jerk_is_the_mean_absolute_change_over_steps_and_dimensions():
    assert played([a(0.0), a(1.0), a(1.0), a(3.0)]).jerk == pytest.approx((1 + 0 + 2) / 3)
    assert played([a(0.0, 1.0), a(2.0, 0.0)]).jerk == pytest.approx((2 + 1) / 2)
    assert played([a(5.0)]).jerk == 0.0


def steps(actions, rewards, decided, acted):
    """Steps where each layer in `acted` contributed 0.5 and the walk reached no other layer."""
    contributions = [{n: np.array([0.5]) for n in a} for a in acted]
    return [StepRecord(*row) for row in zip(actions, rewards, decided, contributions, strict=True)]


def test_measure_episode_counts_decisions_compute_and_activity():
    trace = steps(
        [a(1.0), a(1.0), a(0.2), a(0.2)], [-1.0, -2.0, -0.5, 0.0],
        [("slow", "fast"), ("fast",), (), ("fast",)], [("slow",), ("slow",), ("slow", "fast"), ("slow",)],
    )
    m = measure_episode(trace, {"slow": 10, "fast": 3}, (a(-1.0), a(1.0)))
    assert (m.ret, m.steps, m.repetition, m.repetition_at_bounds, m.decisions) == (-3.5, 4, 0.5, 0.25, 3)
    # held by the rules: step 2 only (slow holds, fast had no part before or after); step 4's 0.2 is fast's anew
    assert m.repetition_held == 0.25
    assert m.jerk == pytest.approx(0.8 / 3)
    assert m.compute == 10 + 3 * 3
    assert m.decided == {"slow": 1, "fast": 3}
    assert m.acted == {"slow": 4, "fast": 1}
    assert m.contribution == {"slow": 2.0, "fast": 0.5}


def test_a_meter_of_several_rows_measures_each_rows_episode_as_its_own_trace_would():
    macs = {"slow": 10, "fast": 3}
    meter = EpisodeMeter(2, list(macs), macs, (a(-1.0), a(10.0)))
    # row 0 plays the episode of the test above; row 1 steps at its 2nd and 4th steps only, then again after
    # its episode is finished (a new one, measured from nothing)
    rows = [np.array([True, False]), np.array([True, True]), np.array([True, False]), np.array([True, True])]
    actions, rewards = [1.0, 1.0, 0.2, 0.2], [-1.0, -2.0, -0.5, 0.0]
    decided = [[1, 1], [0, 1], [0, 0], [0, 1]]
    sizes = [[0.5, 0.0], [0.5, 0.0], [0.5, 0.5], [0.5, 0.0]]
    for t in range(4):
        sized = np.array([sizes[t], [0.0, 0.25]])
        meter.record(rows[t], np.array([[actions[t]], [7.0 + t]]), np.array([rewards[t], 10.0]),
                     np.array([decided[t], [0, 1]], bool), sized, sized > 0)
    row0, row1 = meter.finish(0), meter.finish(1)
    assert (row0.ret, row0.steps, row0.repetition, row0.decisions, row0.compute) == (-3.5, 4, 0.5, 3, 19)
    assert row0.repetition_at_bounds == 0.0, "its repeats, of 1.0 and 0.2, are inside (-1, 10)"
    assert row0.repetition_held == 0.25
    assert row0.jerk == pytest.approx(0.8 / 3)
    assert row0.decided == {"slow": 1, "fast": 3} and row0.acted == {"slow": 4, "fast": 1}
    assert row0.contribution == {"slow": 2.0, "fast": 0.5}
    # row 1: actions 8 then 10 (no repeat, jerk 2), two fast decisions of 3 MACs, fast acting with 0.25 twice
    assert (row1.ret, row1.steps, row1.repetition, row1.jerk, row1.decisions, row1.compute) == (20.0, 2, 0.0, 2.0, 2, 6)
    assert row1.repetition_held == 0.0
    assert row1.decided == {"slow": 0, "fast": 2} and row1.acted == {"slow": 0, "fast": 2}
    assert row1.contribution == {"slow": 0.0, "fast": 0.5}
    meter.record(np.array([False, True]), np.array([[0.0], [10.0]]), np.array([0.0, 1.0]), np.zeros((2, 2), bool),
                 np.zeros((2, 2)), np.zeros((2, 2), bool))
    again = meter.finish(1)
    assert (again.ret, again.steps, again.repetition, again.jerk) == (1.0, 1, 0.0, 0.0), "a new episode's first step"
    for _ in range(2):
        meter.record(np.array([False, True]), np.array([[0.0], [10.0]]), np.array([0.0, 1.0]),
                     np.zeros((2, 2), bool), np.zeros((2, 2)), np.zeros((2, 2), bool))
    last = meter.finish(1)
    assert last.repetition_at_bounds == 0.5, "10 repeated, at the upper bound: one of two steps"
    assert last.repetition_held == 0.5, "no layer decided or had a part: the second step is held"
    for action, fast in ((0.0, 0.0), (5.0, 0.25)):  # an episode without a repeat, the fast layer deciding its second
        sized = np.array([[0.0, 0.0], [0.0, fast]])  # step's action anew: the last one's repeats are not carried
        meter.record(np.array([False, True]), np.array([[0.0], [action]]), np.array([0.0, 1.0]), sized > 0, sized,
                     sized > 0)
    fresh = meter.finish(1)
    assert (fresh.repetition, fresh.repetition_at_bounds, fresh.repetition_held) == (0.0, 0.0, 0.0)


def test_a_meters_rows_measure_bit_for_bit_what_measure_episode_measures_of_their_traces():
    rng, macs = np.random.default_rng(0), {"slow": 10, "fast": 3}
    traces = [[], [], []]
    bounds = (a(-3.0, -3.0), a(0.5, 0.5))
    meter = EpisodeMeter(3, list(macs), macs, bounds)
    for _ in range(60):
        rows = rng.random(3) < 0.7
        action = rng.normal(size=(3, 2)).astype(np.float32)
        action[rng.random(3) < 0.3] = 0.5  # some steps repeat, at the bounds
        action[rng.random(3) < 0.2] = (0.5, 0.0)  # and some not
        reward, decided = rng.normal(size=3), rng.random((3, 2)) < 0.4
        sizes = np.where(rng.random((3, 2)) < 0.5, np.abs(rng.normal(size=(3, 2))), 0.0)
        reached = (sizes > 0) | (rng.random((3, 2)) < 0.5)  # some reached with no part
        meter.record(rows, action, reward, decided, sizes, reached)
        for k in np.flatnonzero(rows):
            contributions = {n: np.array([sizes[k, j]]) for j, n in enumerate(macs) if reached[k, j]}
            traces[k].append(StepRecord(action[k], float(reward[k]), tuple(n for j, n in enumerate(macs)
                                                                             if decided[k, j]), contributions))
    for k in range(3):
        measured = measure_episode(traces[k], macs, bounds)
        assert meter.finish(k) == measured, f"row {k}"
        assert 0 < measured.repetition_held < 1, "the rows' steps are held and not, or the test shows nothing"


def test_summarise_means_returns_and_pools_activity_over_steps():
    e1 = measure_episode(steps([a(0.0)] * 2, [-1.0, -1.0], [("x",), ()], [("x",), ("x",)]), {"x": 7}, (a(0.0), a(1.0)))
    e2 = measure_episode(steps([a(0.0)] * 4, [0.0] * 4, [("x",)] * 4, [()] * 4), {"x": 7}, (a(-1.0), a(1.0)))
    s = summarise([e1, e2])
    assert s.return_mean == pytest.approx(-1.0) and s.return_std == pytest.approx(1.0)
    assert s.decisions == pytest.approx(2.5) and s.repetition == pytest.approx((0.5 + 0.75) / 2)
    assert s.repetition_at_bounds == pytest.approx((0.5 + 0.0) / 2), "e1 repeats 0 at its lower bound, e2 inside"
    assert s.compute == pytest.approx((7 + 28) / 2) and s.jerk == 0.0
    assert s.decided == {"x": pytest.approx(5 / 6)} and s.acted == {"x": pytest.approx(2 / 6)}
    assert s.contribution == {"x": pytest.approx(2 * 0.5 / 6)}
    assert (s.return_min, s.return_max) == (-2.0, 0.0)  # e1's return, e2's
    # e1's repeat is held (x did not decide anew); e3 repeats its action as x decides it again: repeated, not held
    e3 = measure_episode(steps([a(0.0)] * 2, [0.0] * 2, [("x",)] * 2, [("x",)] * 2), {"x": 7}, (a(-1.0), a(1.0)))
    both = summarise([e1, e3])
    assert (both.repetition, both.repetition_held) == (pytest.approx(0.5), pytest.approx(0.25))


def test_distinct_states_spread_by_farthest_point_from_the_first():
    from layered.evaluate import distinct_states

    # on a line: 0 first, then the farthest (10), then the one farthest from both (5 beats 4 and 6)
    points = [np.array([x], np.float32) for x in (0, 1, 4, 5, 6, 10)]
    assert distinct_states(points, 3) == [0, 3, 5]
    assert distinct_states(points, 99) == [0, 1, 2, 3, 4, 5]
    # repeated states are not shown twice, and nothing comes of nothing
    assert distinct_states([np.zeros(2), np.zeros(2), np.ones(2)], 3) == [0, 2]
    assert distinct_states([], 8) == []


def test_normalised_auc_of_two_points_and_of_a_curve_starting_late():
    # two points: one trapezoid; steps 1000 and 3000 over range (0, 100): (0.2 + 0.6) / 2
    assert normalised_auc([1000, 3000], [20, 60], (0, 100)) == pytest.approx(0.4)
    # a curve starting at step 2000 (a resumed phase's view): spans 2000..6000, area 2000*0.5 + 2000*0.75
    assert normalised_auc([2000, 4000, 6000], [0, 100, 50], (0, 100)) == pytest.approx((1000 + 1500) / 4000)
    # several evaluations at one step: its last normalised return
    assert normalised_auc([5, 5, 5], [0, 10, 30], (0, 100)) == pytest.approx(0.3)
    # the first two at one step, then on: still the trapezoid over the span
    assert normalised_auc([0, 0, 10], [0, 0, 100], (0, 100)) == pytest.approx(0.5)


def test_summarise_of_one_episode_is_that_episode():
    e = measure_episode(steps([a(0.0), a(1.0)], [-1.0, -3.0], [("x",), ()], [("x",), ()]), {"x": 2}, UNBOUNDED)
    s = summarise([e])
    assert (s.return_mean, s.return_std, s.return_min, s.return_max, s.steps) == (-4.0, 0.0, -4.0, -4.0, 2.0)
    assert s.decided == {"x": 0.5}
    row = s.row()
    assert list(row) == Evaluation.columns(["x"])
    assert row == {"return_mean": -4.0, "return_std": 0.0, "return_min": -4.0, "return_max": -4.0,
                   "repetition": 0.0, "repetition_at_bounds": 0.0, "repetition_held": 0.0,
                   "jerk": 1.0, "decisions": 1.0, "compute": 2.0, "episode_steps": 2.0,
                   "decided_x": 0.5, "acted_x": 0.5, "contribution_x": 0.25}


@pytest.mark.parametrize("unknown", [("repetition_at_bounds", "repetition_held"), ("repetition_held",)])
def test_a_loop_state_saved_before_a_repetition_measure_was_measured_loads_with_it_unknown(unknown):
    import json

    from layered.runstate import LoopState

    state = LoopState()
    state.curve.append((100, Evaluation(-150.0, 5.0, 0.5, 0.25, 200.0, 2e6, 200.0, {}, {}, {}, -160.0, -140.0, 0.125,
                                        0.0625)))
    data = json.loads(state.to_json())
    assert (data["curve"][0][1]["repetition_at_bounds"], data["curve"][0][1]["repetition_held"]) == (0.125, 0.0625)
    for key in unknown:  # as a checkpoint of an earlier version holds its curve
        del data["curve"][0][1][key]
    step, evaluation = LoopState.from_json(json.dumps(data)).curve[0]
    assert (step, evaluation.return_mean, evaluation.repetition) == (100, -150.0, 0.5)
    assert np.isnan(evaluation.repetition_held)
    assert np.isnan(evaluation.repetition_at_bounds) == ("repetition_at_bounds" in unknown)


def played_by_rules(rules, outputs, steps):
    """One stack's steps as the agent view records them, its layer i deciding `outputs[i](t)` at step t: which
    layers decided, and each reached layer's part of the action."""
    trace, names = [], [layer.name for layer in rules.layers]
    for t in range(steps):
        decided = rules.decide_all(np.zeros((1, 3), np.float32), lambda i, _, rows, t=t: np.array([outputs[i](t)]))
        composition = rules.compose()
        parts = {names[i]: c[0].copy() for i, c in composition.contributions.items() if composition.reached[i][0]}
        trace.append(StepRecord(composition.action[0].copy(), 0.0, tuple(names[i] for i, m in decided.items() if m[0]),
                                parts))
        rules.tick()
    return trace


def evaluation_rules(periods, kinds, threshold=None, **layer_settings):
    """The rules of a stack of `periods` and combiners `kinds` as evaluation runs it (with `threshold`, a fraction
    of the maximum action, at every level), actions in [-2, 2]."""
    from conftest import stack_recipe
    from gymnasium.spaces import Box

    from layered.stack import Stack

    recipe = stack_recipe(periods, kinds)
    layers = [layer.model_copy(update={key: values[k] for key, values in layer_settings.items()})
              for k, layer in enumerate(recipe.layers)]
    return Stack(recipe.model_copy(update={"layers": layers}), Box(-1.0, 1.0, (3,), np.float32),
                 Box(-2.0, 2.0, (1,), np.float32), evaluation=threshold is not None, threshold=threshold).rules


def test_held_repetition_under_a_threshold_counts_the_slow_layers_holds_while_the_fast_one_is_zeroed():
    """slow (period 2) holds 1.0; fast (period 1) is zeroed where its effect is below 0.1 x 2 = 0.2.
    step:   0    1    2    3     4    5
    fast:   0.1  0.1  0.5  0.05  0.0  0.1   (admitted only at step 2)
    action: 1.0  1.0  1.5  1.0   1.0  1.0
    held:   -    yes  no (fast acts)  no (fast acted before)  no (slow decides anew)  yes"""
    rules = evaluation_rules([2, 1], "residual-clip", threshold=0.1)
    fast = [0.1, 0.1, 0.5, 0.05, 0.0, 0.1]
    trace = played_by_rules(rules, [lambda t: [1.0], lambda t: [fast[t]]], 6)
    assert [float(s.action[0]) for s in trace] == [1.0, 1.0, 1.5, 1.0, 1.0, 1.0]
    m = measure_episode(trace, {"l0": 1, "l1": 1}, (a(-2.0), a(2.0)))
    assert (m.repetition, m.repetition_held) == (pytest.approx(3 / 6), pytest.approx(2 / 6))


def test_held_repetition_under_a_gate_counts_the_commits_holds_and_the_zeroed_fast_layers():
    """A gate (period 2) over a fast layer (period 1).
    step:   0         1     2         3     4         5     6         7
    slow:   commit .5  -    commit .5  -    defer      -    defer      -
    fast:   (kept out)      (kept out)      0.2       0.2   0.0       0.0
    action: 0.5       0.5   0.5       0.5   0.2       0.2   0.0       0.0
    held:   -         yes   no        yes   no        no    no        yes
    (at 2 the gate decides anew; at 5 the fast layer's 0.2 is decided anew; at 6 it stops having a part)"""
    rules = evaluation_rules([2, 1], "gate")
    slow = [[0.5, 1.0], None, [0.5, 1.0], None, [0.9, -1.0], None, [0.9, -1.0], None]
    fast = [None, None, None, None, [0.2], [0.2], [0.0], [0.0]]
    trace = played_by_rules(rules, [lambda t: slow[t], lambda t: fast[t]], 8)
    assert [float(s.action[0]) for s in trace] == pytest.approx([0.5, 0.5, 0.5, 0.5, 0.2, 0.2, 0.0, 0.0])
    assert [s.decided for s in trace] == [("l0",), (), ("l0",), (), ("l0", "l1"), ("l1",), ("l0", "l1"), ("l1",)]
    m = measure_episode(trace, {"l0": 1, "l1": 1}, (a(-2.0), a(2.0)))
    assert (m.repetition, m.repetition_held) == (pytest.approx(5 / 8), pytest.approx(3 / 8))


def test_a_single_layer_deciding_every_step_holds_nothing_though_its_actions_repeat():
    trace = played_by_rules(evaluation_rules([1], "residual-clip"), [lambda t: [1.0]], 5)
    m = measure_episode(trace, {"l0": 1}, (a(-2.0), a(2.0)))
    assert (m.repetition, m.repetition_held) == (pytest.approx(4 / 5), 0.0)


@pytest.mark.parametrize(("periods", "kinds", "threshold", "settings"), [
    ([2, 1], "residual-clip", 0.3, {}),
    ([4, 2, 1], ["gate", "residual-clip", "residual-clip"], 0.2, {"delay": [0, 1, 1]}),
    ([2, 1], "gate", None, {"learn_from_commits": [False, True]}),
    ([4, 2, 1], ["gate", "gate", "residual-clip"], None, {"learn_from_commits": [False, False, True]}),
    ([2, 1], "residual-clip", 0.3, {"max_repeat": [3, 1]}),
    ([4, 1], "residual-clip", None, {"delay": [1, 2]}),
    ([4, 2, 1], ["residual-clip", "gate", "residual-clip"], 0.3, {"max_repeat": [2, 1, 1]}),
])
def test_every_step_the_rules_held_repeats_its_action_exactly(periods, kinds, threshold, settings):
    """Random outputs, often zero or the layer's last again, over stacks with thresholds, gates, delays, a layer
    deciding under a committed gate and repeat counts: a held step's action is the step before's, every time."""
    rules = evaluation_rules(periods, kinds, threshold, **settings)
    rng, last = np.random.default_rng(3), {}

    def output(i):
        def decide(t):
            layer = rules.layers[i]
            new = rng.uniform(layer.low, layer.high).astype(np.float32)
            new[: rng.integers(0, 2) if rng.random() < 0.4 else 0] = 0.0  # its action part zero
            last[i] = last.get(i, new) if rng.random() < 0.3 else new
            return last[i]
        return decide

    trace = played_by_rules(rules, [output(i) for i in range(len(periods))], 400)
    names = [layer.name for layer in rules.layers]
    decided = np.array([[n in s.decided for n in names] for s in trace])
    reached = np.array([[n in s.contributions for n in names] for s in trace])
    acted = np.array([[s.size(n) > 0 for n in names] for s in trace])
    kept = held(decided[1:], acted[1:], reached[1:], acted[:-1], reached[:-1])
    actions = np.array([s.action for s in trace])
    repeated = np.all(actions[1:] == actions[:-1], axis=1)
    assert kept.sum() >= 20, "few held steps: the test shows little"
    assert np.all(repeated[kept]), f"held but changed at steps {np.flatnonzero(kept & ~repeated) + 1}"


def test_a_layers_size_is_its_mean_absolute_part_over_the_action_dimensions():
    record = StepRecord(np.array([0.4, 0.0], np.float32), 0.0, ("fast",),
                        {"fast": np.array([0.5, -0.1], np.float32), "slow": np.zeros(2, np.float32)})
    assert record.size("fast") == pytest.approx(0.3)  # (0.5 + 0.1) / 2, not the largest
    assert record.size("slow") == 0.0 and record.size("mid") == 0.0  # no part, and not reached
    assert record.acted == ("fast",)
