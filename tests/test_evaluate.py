"""A single run's evaluations play their episodes side by side, as a group of one seed does: they measure what
the agent view measures playing the same episodes one after another."""

from pathlib import Path

import pytest

from layered.plugins import load_plugins
from layered.agents import make_aec_env
from layered.evaluate import episode_seeds, evaluate, run_episode, states_where_layer_acts
from layered.group_eval import evaluate_run, open_run_evaluator, stacks_over
from layered.learner_set import build_learners
from layered.recipe import load_recipe
from layered.orders import phases_of

ROOT = Path(__file__).resolve().parent.parent
SMALL = ["learner.hidden=[16, 16]"]


@pytest.mark.parametrize("recipe, phase", [
    ("recipes/pendulum/td3.toml", -1),
    ("recipes/pendulum/tla-c.toml", 0),  # the slow layer alone
    ("recipes/pendulum/tla-c.toml", -1),  # residual
    ("recipes/pendulum/tla-o.toml", -1),  # a gate committing and deferring
    ("recipes/pendulum/temporl.toml", -1),  # repeats
    ("recipes/research/pendulum-gate-over-residual-3.toml", -1),  # 3 layers
    ("recipes/inverted-double-pendulum/tla-realtime.toml", -1),  # delays, outputs in flight, early ends
    ("docs/examples/pendulum-centre.toml", -1),  # a plugin's learner, acting one row at a time
])
@pytest.mark.parametrize("episodes", [3, 12])  # fewer episodes than lanes; more, so a lane plays two
def test_a_runs_evaluation_side_by_side_measures_what_the_agent_view_measures(recipe, phase, episodes):
    if "centre" in recipe:
        load_plugins([str(ROOT / "docs/examples/centre.py")])
    r = load_recipe(ROOT / recipe, [] if "centre" in recipe else SMALL)
    check_both_ways(r, list(phases_of(r)[phase].active), episodes)


@pytest.mark.parametrize("threshold", [0.0, 0.5, 1.0])
def test_a_threshold_sweeps_evaluations_measure_what_the_agent_view_measures_at_that_threshold(threshold):
    r = load_recipe(ROOT / "recipes/pendulum/tla-c.toml", SMALL)
    check_both_ways(r, list(phases_of(r)[-1].active), 3, threshold)


def check_both_ways(r, active, episodes, threshold=None):
    """The same learners' evaluation through the agent view and side by side: the same measures."""
    learners = build_learners(r)
    env = make_aec_env(r, active=active, evaluation=True, threshold=threshold, keep_trace=True)
    one_by_one = evaluate(env, learners, episodes, 11)
    env.close()
    evaluator = open_run_evaluator(r, active, episodes)
    if threshold is not None:  # (as a threshold sweep evaluates: a stack at that threshold over the same rows)
        evaluator = stacks_over(r, active, evaluator[2], evaluation=True, threshold=threshold)
    try:
        side_by_side = evaluate_run(evaluator, learners, episodes, 11)
    finally:
        evaluator[2].close()
    assert evaluator[1].rows == min(episodes, 10)
    assert side_by_side.return_mean == pytest.approx(one_by_one.return_mean, rel=1e-5)
    assert side_by_side.return_std == pytest.approx(one_by_one.return_std, rel=1e-4, abs=1e-4)
    assert side_by_side.repetition == one_by_one.repetition and side_by_side.decided == one_by_one.decided
    assert side_by_side.repetition_at_bounds == one_by_one.repetition_at_bounds
    assert side_by_side.steps == one_by_one.steps and side_by_side.acted == one_by_one.acted
    assert side_by_side.compute == one_by_one.compute and side_by_side.decisions == one_by_one.decisions
    assert side_by_side.contribution == pytest.approx(one_by_one.contribution, rel=1e-5)
    assert side_by_side.jerk == pytest.approx(one_by_one.jerk, rel=1e-5)


@pytest.mark.parametrize("bias, at_bounds", [(20.0, 199 / 200), (-20.0, 199 / 200), (0.0, 0.0)])
def test_an_actor_held_at_its_limit_repeats_at_the_action_bounds_and_a_constant_inside_does_not(bias, at_bounds):
    import torch

    r = load_recipe(ROOT / "recipes/pendulum/td3.toml", SMALL)
    learners = build_learners(r)
    with torch.no_grad():  # the actor's output is tanh(bias) whatever it sees: +-1 (torque +-2, the bounds) or 0
        out = learners["fast"].actor.net[-1]
        out.weight.zero_()
        out.bias.fill_(bias)
    env = make_aec_env(r, evaluation=True, keep_trace=True)
    one_by_one = evaluate(env, learners, 2, 11)
    env.close()
    evaluator = open_run_evaluator(r, ["fast"], 2)
    try:
        side_by_side = evaluate_run(evaluator, learners, 2, 11)
    finally:
        evaluator[2].close()
    for measured in (one_by_one, side_by_side):  # Pendulum-v1's 200 steps, each after the first a repeat
        assert (measured.steps, measured.repetition) == (200, 199 / 200)
        assert measured.repetition_at_bounds == at_bounds


@pytest.mark.parametrize("threshold", [None, 0.0, 1.0])
def test_a_gallery_draws_from_layered_evals_episodes_at_its_threshold(threshold):
    r = load_recipe(ROOT / "recipes/pendulum/tla-c.toml", SMALL)
    learners = build_learners(r)
    active = list(phases_of(r)[-1].active)
    env = make_aec_env(r, active=active, evaluation=True, threshold=threshold, keep_trace=True)
    played = [run_episode(env, learners, seed) for seed in episode_seeds(11, 3)]
    env.close()
    acted, steps, shots = states_where_layer_acts(r, learners, active, "fast", 11, 3, threshold, count=4)
    assert steps == 3 * 200 and acted == sum(measures.acted["fast"] for measures in played)
    assert len(shots) == min(4, acted) and len({(episode, step) for episode, step, _, _ in shots}) == len(shots)
    for episode, step, frame, record in shots:
        assert "fast" in record.acted and frame.ndim == 3 and 0 <= episode < 3 and 0 <= step < 200


def test_eval_run_from_python_measures_what_layered_eval_writes(tmp_path):
    import json

    import layered
    from layered.cli import main

    recipe = load_recipe(ROOT / "recipes/pendulum/tla-c.toml", [*SMALL, "learner.batch_size=16", "train.warmup=20",
                                                                 "eval.every=100", "eval.episodes=2",
                                                                 "eval.fresh_episodes=2"])
    layered.train(recipe, tmp_path / "run", max_steps=100, progress=False)
    assert main(["eval", str(tmp_path / "run"), "--episodes", "3", "--threshold", "0.1"]) == 0
    written = json.loads((tmp_path / "run" / "eval" / "threshold-0.1-episodes-3.json").read_text())
    measured = layered.eval_run(tmp_path / "run", episodes=3, threshold=0.1)
    assert (measured.return_mean, measured.repetition, measured.decisions) == (
        written["return_mean"], written["repetition"], written["decisions"])
    ended = json.loads((tmp_path / "run" / "results.json").read_text())["phases"][-1]
    fresh = layered.eval_run(tmp_path / "run", weights="final", fresh=True)
    assert fresh.return_mean == ended["fresh_final_return_mean"]


def test_eval_run_computes_with_the_threads_the_run_trained_with(tmp_path, monkeypatch):
    import torch

    import layered
    from layered import run_evals

    recipe = load_recipe(ROOT / "recipes/pendulum/td3.toml", [*SMALL, "learner.batch_size=16", "train.warmup=20",
                                                              "eval.every=100", "eval.episodes=1"])
    before = torch.get_num_threads()
    seen = []
    monkeypatch.setattr(run_evals, "evaluate_trained", lambda *args: seen.append(torch.get_num_threads()))
    try:
        torch.set_num_threads(1)
        layered.train(recipe, tmp_path / "run", max_steps=50, progress=False)
        torch.set_num_threads(2)
        layered.eval_run(tmp_path / "run")
        assert seen == [1] and torch.get_num_threads() == 2  # as trained within, as before after
        layered.eval_run(tmp_path / "run", threads=2)
        assert seen == [1, 2]
    finally:
        torch.set_num_threads(before)
