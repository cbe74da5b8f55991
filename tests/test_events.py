"""TensorBoard event files: every metrics.csv row as scalars, read back with TensorBoard's own loader."""

import csv

import pytest
from conftest import train_until_stopped
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from layered import load_recipe
from layered.events import tag
from layered.runs import resume, train


def test_tags_of_metrics_columns():
    assert tag("return_mean") == "eval/return"
    assert tag("repetition") == "eval/action_repetition"
    assert tag("acted_fast") == "layer/fast/acted"
    assert tag("contribution_slow") == "layer/slow/contribution"
    assert tag("critic_loss_fast") == "loss/fast/critic"
    assert tag("actor_loss_my_layer") == "loss/my_layer/actor"
    assert tag("phase") is None and tag("step") is None


def scalars(run_dir, phase_dir, name):
    """Steps and values of one scalar, as TensorBoard shows them."""
    events = EventAccumulator(str(run_dir / "tensorboard" / phase_dir))
    events.Reload()
    return [e.step for e in events.Scalars(name)], [e.value for e in events.Scalars(name)]


def same_as_csv(run_dir, phase_dir, phase):
    with (run_dir / "metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["phase"] == str(phase)]
    steps, values = scalars(run_dir, phase_dir, "eval/return")
    return steps == [int(r["step"]) for r in rows] and values == pytest.approx([float(r["return_mean"]) for r in rows])


def test_event_files_hold_every_metrics_row_per_phase(tmp_path, tiny):
    recipe = load_recipe("pendulum/tla-c.toml", [*tiny, "log.tensorboard=true"])
    train(recipe, tmp_path, max_steps=400, progress=False)
    assert sorted(p.name for p in (tmp_path / "tensorboard").iterdir()) == ["phase-0-slow", "phase-1-fast"]
    for phase, folder in enumerate(["phase-0-slow", "phase-1-fast"]):
        assert same_as_csv(tmp_path, folder, phase)
    tags = EventAccumulator(str(tmp_path / "tensorboard" / "phase-1-fast")).Reload().Tags()["scalars"]
    assert {"eval/action_repetition", "eval/decisions", "eval/jerk", "layer/fast/acted", "layer/slow/decided",
            "loss/fast/critic", "loss/fast/actor"} <= set(tags)


def test_resumed_run_drops_events_written_after_its_checkpoint(tmp_path, tiny, monkeypatch):
    recipe = load_recipe("pendulum/tla-c.toml", [*tiny, "log.tensorboard=true"])
    train_until_stopped(monkeypatch, recipe, tmp_path, episodes=1, max_steps=400, progress=False)
    # what a run killed between an evaluation and its next checkpoint leaves behind
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(tmp_path / "tensorboard" / "phase-0-slow")) as stale:
        stale.add_scalar("eval/return", -1e6, 300)
    resume(tmp_path, max_steps=400, progress=False)
    assert same_as_csv(tmp_path, "phase-0-slow", 0)


def test_each_seed_of_a_group_writes_its_own_event_files(tmp_path, tiny):
    from layered.group import group_recipes, train_group

    recipes = group_recipes("pendulum/tla-c.toml", [0, 1], [*tiny, "log.tensorboard=true"])
    train_group(recipes, [tmp_path / "seed0", tmp_path / "seed1"], "pendulum/tla-c", max_steps=300, progress=False)
    for seed in ("seed0", "seed1"):
        for phase, folder in enumerate(["phase-0-slow", "phase-1-fast"]):
            assert same_as_csv(tmp_path / seed, folder, phase)
