"""Brief training on real environments: every shipped recipe, deep stacks, determinism, the CLI."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import layered_here, stack_recipe

from layered import load_recipe
from layered.interrupt import StopRequest
from layered.run_logs import RunLogs
from layered.replay_journal import ReplayJournal
from layered.runstate import LoopState
from layered.checkpoint import load_checkpoint
from layered.learner_set import build_learners
from layered.runs import train
from layered.orders import phases_of
from layered.trainer import Training, run_phase

RECIPES = sorted((Path(__file__).parent.parent / "recipes").rglob("*.toml"))
PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
        "eval.every=100", "eval.episodes=1", "eval.fresh_episodes=2"]


def check_run(out: Path, phases: int, layers: list[str]) -> dict:
    results = json.loads((out / "results.json").read_text())
    assert len(results["phases"]) == phases
    final = results["phases"][-1]
    for key in ("return_mean", "return_std", "auc", "repetition", "decisions", "episode_steps"):
        assert final[key] is not None
    assert 0 <= final["repetition"] <= 1 and 0 < final["decisions"] <= final["episode_steps"]
    assert 0 <= final["repetition_at_bounds"] <= final["repetition"]
    assert {f"decided_{n}" for n in final["active"]} <= set(final)
    for name in layers:
        assert (out / "checkpoints" / f"{name}.pt").exists()
    assert (out / "curves.png").stat().st_size > 0 and (out / "recipe.toml").exists()
    assert (out / "metrics.csv").read_text().count("\n") >= 2 * phases
    return results


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: str(p.relative_to(p.parents[1])))
def test_every_shipped_recipe_trains_briefly(path, tmp_path):
    steps = 300  # an evaluation at each phase's start and end, one fresh episode: dm_control's episodes are 1000 steps
    recipe = load_recipe(path, [*TINY, f"eval.every={steps}", "eval.fresh_episodes=1"])
    train(recipe, tmp_path, max_steps=steps, progress=False)
    check_run(tmp_path, len(phases_of(recipe)), recipe.layer_names())


@pytest.mark.parametrize(
    "kinds", [["residual-clip"] * 3, ["gate", "gate", "residual-clip"], ["gate", "residual-clip", "residual-clip"]],
    ids=["residual", "gated", "gate-over-residual"],
)
@pytest.mark.parametrize("order", ["slow-to-fast", "fast-to-slow"])
def test_three_layer_stacks_train_and_report_every_metric(kinds, order, tmp_path):
    recipe = load_recipe(stack_recipe([4, 2, 1], kinds).model_dump(), [*TINY, f"train.order={order}"])
    train(recipe, tmp_path, max_steps=200, progress=False)
    results = check_run(tmp_path, 3, ["l0", "l1", "l2"])
    assert results["phases"][-1]["active"] == ["l0", "l1", "l2"]


@pytest.mark.parametrize("order", ["slow-to-fast", "fast-to-slow", "joint"])
def test_four_layer_mixed_stack_trains_in_every_order(order, tmp_path):
    kinds = ["gate", "residual-clip", "gate", "residual-clip"]
    recipe = load_recipe(stack_recipe([8, 4, 2, 1], kinds).model_dump(), [*TINY, f"train.order={order}"])
    train(recipe, tmp_path, max_steps=200, progress=False)
    results = check_run(tmp_path, 1 if order == "joint" else 4, ["l0", "l1", "l2", "l3"])
    assert results["phases"][-1]["active"] == ["l0", "l1", "l2", "l3"]


def test_explicit_phases_with_two_layers_learning_at_once(tmp_path):
    data = stack_recipe([4, 1], "gate").model_dump()
    data["train"] = {"phases": [{"learn": ["l1"]}, {"learn": ["l0", "l1"], "steps": 150}]}
    train(load_recipe(data, TINY), tmp_path, max_steps=200, progress=False)
    results = check_run(tmp_path, 2, ["l0", "l1"])
    assert [p["steps"] for p in results["phases"]] == [200, 150]


def test_same_seed_gives_the_same_run(tmp_path):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    for name in ("a", "b"):
        train(recipe, tmp_path / name, max_steps=250, progress=False)
    assert (tmp_path / "a" / "metrics.csv").read_text() == (tmp_path / "b" / "metrics.csv").read_text()
    assert (tmp_path / "a" / "episodes.csv").read_text() == (tmp_path / "b" / "episodes.csv").read_text()


def layered_cli(*args):
    return subprocess.run([sys.executable, "-m", "layered.cli", *map(str, args)], capture_output=True, text=True)


@pytest.mark.parametrize("recipe, active, thresholded", [
    ("pendulum/tla-c.toml", ["slow", "fast"], True),  # the residual's threshold holds back the fast layer
    ("pendulum/tla-c.toml", ["slow"], False),  # its slow phase: nothing below the slow layer
    ("pendulum/td3.toml", ["fast"], False),
    ("pendulum/tla-o.toml", ["slow", "fast"], False),  # a gate has no threshold
    ("research/pendulum-gate-over-residual-3.toml", ["slow", "mid", "fast"], True),
    ("research/pendulum-gate-over-residual-3.toml", ["slow", "mid"], False),  # the gate over mid: no fast below
    ("research/pendulum-gate-over-residual-3.toml", ["mid", "fast"], True),
])
def test_a_threshold_acts_where_a_thresholded_combiner_has_a_faster_layer_present(recipe, active, thresholded):
    from layered.stack import has_threshold

    assert has_threshold(load_recipe(PENDULUM.parent / recipe), active) is thresholded


def test_cli_train_then_eval_with_threshold(tmp_path):
    out = tmp_path / "run"
    recipe = PENDULUM / "tla-c.toml"
    proc = layered_cli("train", recipe, *TINY, "eval.episodes=3", "--steps", 200, "--seed", 4, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "| phase | learns |" in proc.stdout and "phase 1: fast" in proc.stderr  # table and progress
    assert load_recipe(out / "recipe.toml").train.seed == 4
    assert layered_cli("eval", out, "--weights", "final").returncode == 0  # training's last evaluation again
    again = json.loads((out / "eval" / "weights-final" / "threshold-recipe-episodes-3.json").read_text())
    last = list(csv.DictReader((out / "metrics.csv").open()))[-1]
    assert [float(last[k]) for k in ("return_mean", "return_std", "jerk")] == [again[k] for k in
                                                                                ("return_mean", "return_std", "jerk")]
    proc = layered_cli("eval", out, "--weights", "final", "--fresh")  # the end of training's fresh episodes again
    assert proc.returncode == 0, proc.stderr
    fresh = json.loads((out / "eval" / "weights-final" / "fresh" / "threshold-recipe-episodes-2.json").read_text())
    ended = json.loads((out / "results.json").read_text())["phases"][-1]
    measures = ("return_mean", "return_std", "repetition", "repetition_at_bounds", "decisions", "jerk")
    assert [fresh[k] for k in measures] == [ended[f"fresh_final_{k}"] for k in measures]
    assert fresh["return_mean"] != again["return_mean"], "other episodes than those of training's evaluations"
    proc = layered_cli("eval", out, "--episodes", 2, "--threshold", 0.0, "--plot")
    assert proc.returncode == 0, proc.stderr
    written = json.loads((out / "eval" / "threshold-0.0-episodes-2.json").read_text())
    assert (out / "eval" / "threshold-0.0-episodes-2.png").stat().st_size > 0
    assert f"{written['return_mean']:.1f}" in proc.stdout and "evaluating" in proc.stderr

    proc = layered_cli("eval", out, "--episodes", 1, "--threshold-sweep", "0,0.5", "--gallery")
    assert proc.returncode == 0, proc.stderr
    # (on 1 episode, where the recipe evaluates on more: a name of its own, which says so)
    assert (out / "eval" / "threshold-sweep-0-0.5-episodes-1.csv").read_text().count("\n") == 3  # two thresholds
    assert (out / "eval" / "threshold-sweep-0-0.5-episodes-1.png").stat().st_size > 0
    assert (out / "eval" / "gallery-fast.png").stat().st_size > 0
    assert layered_here("eval", out, "--gallery", "medium").returncode == 2

    before = sorted(p.name for p in out.iterdir())
    assert layered_here("train", recipe, "--out", out).returncode == 2  # never overwrites a run
    assert sorted(p.name for p in out.iterdir()) == before
    (out / "checkpoints" / "fast.best.pt").write_bytes(b"\0" * 10)  # the recipe hands on its best weights
    proc = layered_here("eval", out)
    assert proc.returncode == 2 and "not a checkpoint" in proc.stderr and "Traceback" not in proc.stderr


def first_phase(recipe, out: Path, steps: int):
    """The learners and loop state after the recipe's first phase, run alone for `steps` steps, logging in `out`."""
    out.mkdir()
    learners = build_learners(recipe)
    logs = RunLogs.open(out, recipe)
    logs.begin()
    run = Training(recipe, learners, logs, out / "run.pt", None, False, StopRequest(), ReplayJournal(out / "replay"))
    state, phase = LoopState(), phases_of(recipe)[0]
    state.start_phase(0, phase.learn, recipe.eval.every, recipe.eval.every)
    run_phase(run, state, phase, steps)
    return learners, state


def test_time_limit_truncation_bootstraps_and_termination_does_not(tmp_path):
    for env_id, terminates in (("Pendulum-v1", False), ("InvertedPendulum-v5", True)):
        recipe = load_recipe(stack_recipe([1], env=env_id).model_dump(), [*TINY, "train.warmup=1000"])
        learners, _ = first_phase(recipe, tmp_path / env_id, 450)
        buffer = learners["l0"].buffer
        not_done = buffer.fields()["not_done"]
        assert len(buffer) >= 400  # Pendulum: two truncated episodes stored whole
        assert bool((not_done == 0).any()) is terminates


@pytest.mark.parametrize("select", ["final", "best"])
def test_each_phase_keeps_final_and_best_weights_reports_both_fresh_and_hands_on_the_selected(select, tmp_path):
    import csv

    import torch

    from layered.learner_set import load_learners

    recipe = load_recipe(PENDULUM / "tla-c.toml", [*TINY, f"train.select={select}", "eval.fresh_episodes=3"])
    train(recipe, tmp_path, max_steps=600, progress=False)
    rows = json.loads((tmp_path / "results.json").read_text())["phases"]
    with (tmp_path / "metrics.csv").open() as f:
        metrics = list(csv.DictReader(f))
    for row in rows:
        curve = [(int(m["step"]), float(m["return_mean"])) for m in metrics if m["phase"] == str(row["phase"])]
        best = max(curve, key=lambda point: point[1])
        assert (row["best_step"], row["best_return_mean"]) == best  # the earliest best evaluation of the phase
        measures = ("return_mean", "return_std", "repetition", "repetition_at_bounds", "decisions")
        assert {f"fresh_{weights}_{k}" for weights in ("final", "best") for k in measures} <= set(row)
    assert "Final and best weights of each phase" in (tmp_path / "results.md").read_text()
    slow = {name: load_checkpoint(tmp_path / "checkpoints" / name, "slow")["actor"]
            for name in ("slow.pt", "slow.best.pt")}
    handed_on = load_checkpoint(tmp_path / "checkpoints" / "run.pt", "run")["learners"]["slow"]
    chosen = slow["slow.best.pt" if select == "best" else "slow.pt"]
    assert all(torch.equal(chosen[k], handed_on["policy"]["actor"][k]) for k in chosen)
    if rows[0]["best_step"] != rows[0]["steps"]:  # the best was not the last evaluation: the two differ
        assert not all(torch.equal(slow["slow.pt"][k], slow["slow.best.pt"][k]) for k in chosen)
    fast = {name: load_checkpoint(tmp_path / "checkpoints" / name, "fast")["actor"]
            for name in ("fast.pt", "fast.best.pt")}
    for weights, saved in (("final", "fast.pt"), ("best", "fast.best.pt")):  # the slow layer always as handed on
        learners = load_learners(recipe, tmp_path, weights)
        assert all(torch.equal(chosen[k], learners["slow"].actor.state_dict()[k]) for k in chosen)
        assert all(torch.equal(fast[saved][k], learners["fast"].actor.state_dict()[k]) for k in fast[saved])


def test_a_layer_starts_from_another_runs_weights_and_the_run_keeps_a_copy(tmp_path):
    import torch

    from layered.recipe import RecipeError
    from layered.learner_set import load_learners

    train(load_recipe(PENDULUM / "tla-c.toml", TINY), tmp_path / "a", max_steps=300, progress=False)
    source = load_checkpoint(tmp_path / "a" / "checkpoints" / "slow.best.pt", "slow")["actor"]
    recipe_file = tmp_path / "recipes" / "fast-on-a.toml"  # `weights` is relative to the file that sets it
    recipe_file.parent.mkdir()
    recipe_file.write_text(f'extends = "{PENDULUM / "tla-c.toml"}"\n'
                           '[[layers]]\nname = "slow"\nperiod = 4\nweights = "../a/checkpoints/slow.best.pt"\n'
                           '[[layers]]\nname = "fast"\nperiod = 1\nsees = ["obs", "slow"]\naction_scale = 2.0\n'
                           'action_penalty = 1.0\n'
                           '[train]\norder = "explicit"\nphases = [{ learn = ["fast"], active = ["slow", "fast"] }]\n')
    recipe = load_recipe(recipe_file, TINY)
    assert recipe.layers[0].weights == str(tmp_path / "a" / "checkpoints" / "slow.best.pt")
    train(recipe, tmp_path / "b", max_steps=300, progress=False)
    check_run(tmp_path / "b", phases=1, layers=["slow", "fast"])
    (tmp_path / "a" / "checkpoints" / "slow.best.pt").unlink()  # the run evaluates from its own copy
    learners = load_learners(load_recipe(tmp_path / "b" / "recipe.toml"), tmp_path / "b")
    assert all(torch.equal(learners["slow"].actor.state_dict()[k], source[k]) for k in source)

    for weights, message in [("missing.pt", "no checkpoint for layer 'slow'"),
                             (tmp_path / "a" / "checkpoints" / "fast.pt", "not a checkpoint of 'slow'")]:
        with pytest.raises(RecipeError, match=rf"layers\[0\]\.weights: .*{message}"):
            train(load_recipe(recipe_file, [*TINY, f"layers.slow.weights={weights}"]), tmp_path / "c", progress=False)
    with pytest.raises(RecipeError, match=r"layers\[0\]\.weights: .*does not fit layer 'slow'"):
        train(load_recipe(recipe_file, [*TINY, "learner.hidden=[16, 16]",
                                        f"layers.slow.weights={tmp_path / 'a' / 'checkpoints' / 'slow.pt'}"]),
              tmp_path / "c", progress=False)
    assert not (tmp_path / "c").exists()  # refused before anything was written


def joint_phase(out: Path, overrides: list[str]):
    """The learners and loop state after 400 steps of the gated Pendulum recipe's joint phase."""
    return first_phase(load_recipe(PENDULUM / "tla-joint.toml", [*TINY, *overrides]), out, 400)


def test_a_fast_layer_that_learns_from_commits_stores_a_one_step_transition_at_every_step(tmp_path):
    step_discount = "train.discount=step"  # gamma**k for a transition of k steps: shows each one's length
    learners, state = joint_phase(tmp_path / "a", [step_discount, "layers.fast.learn_from_commits=true"])
    # 400 steps, two whole 200-step episodes: the fast layer decided at every one
    assert state.decisions["fast"] == 400 and len(learners["fast"].buffer) == 400
    assert learners["fast"].buffer.fields()["discount"].unique().tolist() == [pytest.approx(0.99)]
    learners, state = joint_phase(tmp_path / "b", [step_discount, "layers.fast.learn_from_commits=false"])
    assert state.decisions["fast"] < 400  # without: only the steps the gate deferred, some spanning commits
    assert learners["fast"].buffer.fields()["discount"].min() < 0.98


def test_a_layer_makes_its_updates_after_each_decision_once_it_learns(tmp_path):
    one, state = joint_phase(tmp_path / "a", ["layers.slow.warmup=10", "layers.slow.updates=1"])
    three, state_three = joint_phase(tmp_path / "b", ["layers.slow.warmup=10", "layers.slow.updates=3"])
    decisions = state.decisions["slow"]
    assert decisions == state_three.decisions["slow"] == 68  # 2 x ceil(200 / 6): the period's own schedule
    assert one["slow"].td3.updates == decisions - 10 and three["slow"].td3.updates == 3 * (decisions - 10)


def test_a_recipe_named_by_its_bare_file_name_is_labelled_by_its_folder_as_a_sweep_labels_it(tmp_path, tiny,
                                                                                            monkeypatch):
    (tmp_path / "mine.toml").write_text((Path(__file__).parent.parent / "recipes/pendulum/td3.toml").read_text())
    monkeypatch.chdir(tmp_path)
    assert layered_here("train", "mine.toml", "--steps", 60, *tiny, "--out", "run").returncode == 0
    assert json.loads((tmp_path / "run" / "run.json").read_text())["label"] == f"{tmp_path.name}/mine"
