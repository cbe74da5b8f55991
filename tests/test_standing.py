"""An unfinished run evaluated as it stands: the stack of the phase under way at its last checkpoint, its learning
layers at their best weights so far (or, `--weights final`, at their weights there), read from the run's or the
group's checkpoint without touching the files its writer may be at work on; export and deploy refused until the
run ends."""

import json
from pathlib import Path

import pytest
import torch
from conftest import stop_at, train_until_stopped

import layered.trainer as trainer_module
from layered import load_recipe
from layered.interrupt import Stopped
from layered.runs import train
from layered.checkpoint import load_checkpoint
from layered.cli import main
from layered.group import group_class, seed_weights
from layered.learner_set import build_learners
from layered.rundir import RUN_CHECKPOINT, RunDirError, prepare_run_dir, RunInfo
from layered.run_evals import open_run
from layered.standing import standing

ROOT = Path(__file__).resolve().parent.parent
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50", "eval.every=150", "eval.episodes=1",
        "eval.fresh_episodes=1"]


def same_weights(learner, state):
    """Whether a learner holds the actor of the learner state `state`."""
    held = learner.state_dict()["actor"]
    return all(torch.equal(held[key], value) for key, value in state["actor"].items())


@pytest.mark.parametrize("episodes, phase, present", [(2, 0, ["slow"]), (6, 1, ["slow", "fast"])])
def test_a_stopped_run_is_evaluated_at_its_best_weights_so_far(tmp_path, monkeypatch, capsys, episodes, phase,
                                                               present):
    recipe = load_recipe(ROOT / "recipes/pendulum/tla-c.toml", TINY)
    out = tmp_path / "run"
    train_until_stopped(monkeypatch, recipe, out, episodes, max_steps=700, progress=False)
    saved = load_checkpoint(out / RUN_CHECKPOINT, "run")
    loop = json.loads(saved["loop"])
    best_step, best = max(loop["curve"], key=lambda point: point[1]["return_mean"])  # (no ties in these runs)
    assert (loop["phase"], set(saved["best"])) == (phase, {present[-1]})

    run = open_run(out, unfinished=True)
    assert (run.active, run.standing.step, run.standing.best_step) == (present, loop["step"], best_step)
    assert run.standing.best_return == best["return_mean"]
    assert same_weights(run.learners[present[-1]], saved["best"][present[-1]])
    if phase == 1:  # the slow layer as phase 0 handed it on (train.select: best)
        assert same_weights(run.learners["slow"], load_checkpoint(out / "checkpoints/slow.best.pt", "slow"))
    assert main(["eval", str(out), "--episodes", "2"] + ["--threshold", "0.2"] * (phase == 0)) == 0
    err = capsys.readouterr().err
    assert ("no layer of this stack (slow) has a contribution that a threshold holds back" in err) is (phase == 0)
    assert f"{out} has stopped: at its last checkpoint phase {phase} was at step {loop['step']}" in err
    assert f"evaluating '{present[-1]}' at the best weights so far (evaluated at step {best_step}" in err
    threshold = "0.2" if phase == 0 else "recipe"
    written = out / "eval" / "unfinished" / f"phase{phase}-best-{best_step}" / f"threshold-{threshold}-episodes-2.json"
    assert json.loads(written.read_text())["active"] == present
    assert not (out / "eval" / f"threshold-{threshold}-episodes-2.json").exists()  # apart from what a report reads

    latest = open_run(out, "final", unfinished=True)  # the learning layer as the checkpoint holds it
    assert same_weights(latest.learners[present[-1]], saved["learners"][present[-1]]["policy"])
    assert not same_weights(latest.learners[present[-1]], saved["best"][present[-1]])
    if phase == 1:
        assert same_weights(latest.learners["slow"], load_checkpoint(out / "checkpoints/slow.best.pt", "slow"))
    capsys.readouterr()
    assert main(["eval", str(out), "--episodes", "1", "--weights", "final"]) == 0
    assert f"phase {phase} was at step {loop['step']}; evaluating '{present[-1]}' at its weights there" in \
        capsys.readouterr().err
    assert (out / f"eval/unfinished/phase{phase}-step-{loop['step']}/weights-final/"
            "threshold-recipe-episodes-1.json").exists()
    assert main(["export", str(out), "--format", "torchscript"]) == 2
    refused = capsys.readouterr().err
    assert f"{out} has not finished (at its last checkpoint phase {phase} was at step" in refused
    assert f"`layered resume {out}` finishes it, then try again" in refused
    assert not (out / "export-torchscript").exists()


def test_a_run_stopped_between_phases_is_evaluated_as_the_phase_before_ended(tmp_path, monkeypatch, capsys):
    finish = trainer_module._finish_phase

    def stop_while_finishing(run, *args):
        run.stop.requested = "SIGINT"  # as a signal during the phase's last evaluations would
        return finish(run, *args)

    monkeypatch.setattr(trainer_module, "_finish_phase", stop_while_finishing)
    out = tmp_path / "run"
    with pytest.raises(Stopped):
        train(load_recipe(ROOT / "recipes/pendulum/tla-c.toml", TINY), out, max_steps=300, progress=False)
    monkeypatch.undo()
    at = standing(out, 0)
    assert (at.phase, at.best, at.stack_phase, at.folder(), at.folder(latest=True)) == (
        1, {}, 0, "unfinished/phase0-end", "unfinished/phase0-end")
    run = open_run(out, unfinished=True)
    assert run.active == ["slow"]
    assert same_weights(run.learners["slow"], load_checkpoint(out / "checkpoints/slow.best.pt", "slow"))
    assert main(["eval", str(out), "--episodes", "1", "--weights", "final"]) == 0
    assert "at its last checkpoint phase 0 had ended; evaluating every layer as that phase handed it on" in \
        capsys.readouterr().err
    assert (out / "eval/unfinished/phase0-end/weights-final/threshold-recipe-episodes-1.json").exists()


def test_a_group_seed_is_read_from_the_groups_checkpoint_and_nothing_there_is_touched(tmp_path, monkeypatch, capsys):
    out = tmp_path / "group"
    stop_at(monkeypatch, [(1, 120)])
    assert main(["train", str(ROOT / "recipes/pendulum/tla-c.toml"), "--seeds", "0,3", "--steps", "300", *TINY,
                 "train.checkpoint_every=100", "--out", str(out)]) == 130
    monkeypatch.undo()
    writing = out / ".group.pt.abc123"  # a checkpoint the group's writer would be writing now
    writing.write_bytes(b"partial")
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())

    saved = load_checkpoint(out / "group.pt", "group")
    state = json.loads(saved["states"][1])
    at = standing(out / "seed3", 3)
    best = load_checkpoint(out / "best" / saved["best"]["files"][1]["file"], "best weights")
    assert (at.phase, at.step, at.stack_phase) == (1, 120, 1) == (state["phase"], state["step"], 1)
    assert at.best_step == max(state["curve"], key=lambda point: point[1]["return_mean"])[0]
    run = open_run(out / "seed3", unfinished=True)
    assert same_weights(run.learners["fast"], best["fast"])
    assert same_weights(run.learners["slow"], load_checkpoint(out / "seed3/checkpoints/slow.best.pt", "slow"))
    assert main(["eval", str(out / "seed3"), "--episodes", "1"]) == 0
    assert "seed3 has stopped: at its last checkpoint phase 1 was at step 120" in capsys.readouterr().err
    latest = open_run(out / "seed3", "final", unfinished=True)  # seed 3 is the group's second row: [1]
    stacked = saved["learners"]["fast"]["nets"]["actor"]  # [K, in, out] weights, [K, 1, out] biases, by layer
    held = latest.learners["fast"].state_dict()["actor"]
    for j, layer in enumerate((0, 2, 4)):  # (an nn.Sequential of linear layers and ReLUs)
        assert torch.equal(held[f"net.{layer}.weight"], stacked[f"stacked.{2 * j}"][1].T)
        assert torch.equal(held[f"net.{layer}.bias"], stacked[f"stacked.{2 * j + 1}"][1].reshape(-1))
    assert not same_weights(latest.learners["fast"], best["fast"])
    assert same_weights(latest.learners["slow"], load_checkpoint(out / "seed3/checkpoints/slow.best.pt", "slow"))
    assert main(["eval", str(out / "seed3"), "--episodes", "1", "--weights", "final"]) == 0
    alone = out / "seed3/eval/unfinished/phase1-step-120/weights-final/threshold-recipe-episodes-1.json"
    # the group as it stands, evaluated as a group: each seed where it stands, seed 3 as it was evaluated alone
    assert main(["eval", str(out), "--episodes", "1", "--weights", "final"]) == 0
    together = json.loads(alone.with_name("threshold-recipe-episodes-1-group.json").read_text())
    assert together["return_mean"] == pytest.approx(json.loads(alone.read_text())["return_mean"], rel=1e-5)
    assert (out / "seed0/eval/unfinished/phase1-step-120/weights-final/threshold-recipe-episodes-1-group.json").exists()
    assert writing.read_bytes() == b"partial"
    assert sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file() and "eval" not in p.parts) == files


def test_a_run_without_a_checkpoint_has_nothing_to_evaluate(tmp_path, capsys):
    recipe = ROOT / "recipes/pendulum/td3.toml"
    prepare_run_dir(tmp_path, recipe.read_text(), RunInfo("x", None, ()), resume=False)
    with pytest.raises(RunDirError, match="has not finished and has no checkpoint yet"):
        open_run(tmp_path, unfinished=True)
    assert main(["eval", str(tmp_path)]) == 2
    assert "no checkpoint yet" in capsys.readouterr().err


def tensors(state, path=""):
    """Every tensor in a nested learner state, by its path of keys, but generator states (a group has its own)."""
    if isinstance(state, torch.Tensor):
        return {} if "rng" in path else {path: state}
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, list | tuple) else []
    return {key: value for k, v in items for key, value in tensors(v, f"{path}/{k}").items()}


@pytest.mark.parametrize("name, kinds", [("td3", {"td3"}), ("temporl", {"temporl"}),
                                         ("tla-joint", {"td3-gate", "td3"})])
def test_a_seeds_weights_are_taken_out_of_its_groups_learner_states(name, kinds):
    recipes = [load_recipe(ROOT / f"recipes/pendulum/{name}.toml", ["learner.hidden=[8, 8]", f"train.seed={k}"])
               for k in range(3)]
    assert {recipes[0].learner_config(i).kind for i in range(len(recipes[0].layers))} == kinds  # every kind of group
    singles = [build_learners(recipe, device="cpu") for recipe in recipes]  # (each seed starts from weights of its own)
    states = {layer: group_class(recipes[0].learner_config(i).kind)([seed[layer] for seed in singles]).resume_state()
              for i, layer in enumerate(recipes[0].layer_names())}
    taken = seed_weights(recipes[0], states, 1, 3)
    for layer, weights in taken.items():
        own = tensors(singles[1][layer].state_dict())
        assert tensors(weights).keys() == own.keys()
        assert all(torch.equal(value, own[key]) for key, value in tensors(weights).items()), layer
