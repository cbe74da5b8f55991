"""Runs that survive anything: killed or stopped at any moment, a resumed run ends byte for byte
as one that never stopped; changed recipes, changed budgets and damaged checkpoints are refused."""

import copy
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_same_run, between_checkpoints, kill_when, stop_at_episode_end, train_until_stopped

import layered.group as group_module
import layered.trainer as trainer_module
from layered import load_recipe
from layered.cli import main
from layered.checkpoint import CheckpointError, load_checkpoint, previous, save_checkpoint
from layered.learner_set import build_learners
from layered.recipe import resolved
from layered.replay_journal import ReplayJournal, replay_folder
from layered.runstate import load_state, recipe_digest
from layered.interrupt import Stopped
from layered.rundir import RunDirError, read_run_info, writer
from layered.runs import resume, train
from layered.errors import Diverged

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
        "eval.every=150", "eval.episodes=1", "eval.fresh_episodes=2"]


def test_a_recipes_digest_leaves_out_how_the_environments_processes_wait_and_nothing_else():
    recipe = resolved(load_recipe(PENDULUM / "tla-c.toml"))
    earlier = copy.deepcopy(recipe)
    del earlier["env"]["wait"]  # as versions before the setting resolved it, and digested it whole:
    assert recipe_digest(recipe) == hashlib.sha256(json.dumps(earlier, sort_keys=True).encode()).hexdigest()
    spinning = copy.deepcopy(recipe)
    spinning["env"]["wait"] = "spin"
    assert recipe_digest(spinning) == recipe_digest(recipe)
    for section, key, value in (("env", "workers", 3), ("env", "threads", 2), ("train", "seed", 7)):
        other = copy.deepcopy(recipe)
        other[section][key] = value
        assert recipe_digest(other) != recipe_digest(recipe), f"{section}.{key}"


def test_a_run_stopped_at_an_episode_end_resumes_to_the_same_files(tmp_path, monkeypatch):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "whole", max_steps=700, progress=False, label="x")
    for k in (1, 3, 4, 6):  # first phase, both sides of the phase end, second phase
        monkeypatch.undo()
        stop_at_episode_end(monkeypatch, k)
        out = tmp_path / f"stopped-{k}"
        with pytest.raises(Stopped) as stopped:
            train(recipe, out, max_steps=700, progress=False, label="x")
        assert f"layered resume {out}" in str(stopped.value) and not (out / "results.json").exists()
        monkeypatch.undo()
        train(recipe, out, max_steps=700, progress=False, label="x", resume=True)
        assert_same_run(tmp_path / "whole", out)


def test_metrics_keep_every_layers_columns_in_every_phase(tmp_path):
    train(load_recipe(PENDULUM / "tla-c.toml", TINY), tmp_path, max_steps=300, progress=False)
    header, *rows = (tmp_path / "metrics.csv").read_text().splitlines()
    assert "decided_fast" in header and "critic_loss_fast" in header and "acted_slow" in header
    fast = header.split(",").index("acted_fast")
    assert {row.split(",")[0] for row in rows} == {"0", "1"}
    assert all((row.split(",")[fast] == "") == (row.split(",")[0] == "0") for row in rows)  # fast present in phase 1


def test_resume_refuses_a_changed_recipe_or_budget_naming_the_difference(tmp_path, monkeypatch):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train_until_stopped(monkeypatch, recipe, tmp_path, 2, max_steps=700, progress=False)
    with pytest.raises(RunDirError, match="started with --steps 700, not --steps 900"):
        resume(tmp_path, max_steps=900)
    changed = load_recipe(PENDULUM / "tla-c.toml", [*TINY, "train.warmup=60", "env.wait=spin"])
    with pytest.raises(CheckpointError, match=r"recipe differs .*\(train\.warmup: 50 -> 60\)$"):
        train(changed, tmp_path, max_steps=700, progress=False, resume=True)  # (env.wait changes no number)
    with pytest.raises(RunDirError, match="holds a stopped run; continue it with `layered resume"):
        train(recipe, tmp_path, max_steps=700, progress=False)
    resume(tmp_path, progress=False)
    assert (tmp_path / "results.json").exists()


def test_a_damaged_checkpoint_falls_back_to_the_previous_one(tmp_path, monkeypatch, capsys):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "whole", max_steps=700, progress=False, label="x")
    out = tmp_path / "run"
    train_until_stopped(monkeypatch, recipe, out, 3, max_steps=700, progress=False, label="x")
    newest = out / "checkpoints" / "run.pt"
    assert previous(newest).exists()
    newest.write_bytes(newest.read_bytes()[:1000])  # truncated
    (out / "checkpoints" / ".run.pt.abc123").write_bytes(b"half a write")  # a write cut off by a kill
    resume(out, progress=False)
    assert "using the previous checkpoint run.prev.pt" in capsys.readouterr().err
    assert_same_run(tmp_path / "whole", out)
    assert not list((out / "checkpoints").glob(".run.pt.*"))


def test_a_damaged_replay_segment_falls_back_to_the_previous_checkpoint(tmp_path, monkeypatch, capsys):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "whole", max_steps=700, progress=False, label="x")
    out = tmp_path / "run"
    train_until_stopped(monkeypatch, recipe, out, 3, max_steps=700, progress=False, label="x")
    newest = load_checkpoint(out / "checkpoints" / "run.pt", "run")["replays"]["slow.td3"]["segments"][-1]
    segment = out / "checkpoints" / "replay" / newest["file"]
    segment.write_bytes(segment.read_bytes()[:-3])
    resume(out, progress=False)
    assert "using the previous checkpoint run.prev.pt" in capsys.readouterr().err
    assert_same_run(tmp_path / "whole", out)


def test_a_run_stopped_by_layered_0_1_0_resumes_with_the_buffers_its_checkpoint_holds(tmp_path, monkeypatch):
    """Its checkpoint held each TD3 buffer's fields in the learner's resume state and named no segments."""
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "whole", max_steps=700, progress=False, label="x")
    out = tmp_path / "run"
    train_until_stopped(monkeypatch, recipe, out, 3, max_steps=700, progress=False, label="x")
    checkpoint = out / "checkpoints" / "run.pt"
    saved, learners = load_checkpoint(checkpoint, "run"), build_learners(recipe)
    load_state(checkpoint, learners, resolved(recipe), 700, ReplayJournal(replay_folder(checkpoint)))
    for name, learner in learners.items():
        buffer = learner.buffer
        saved["learners"][name]["buffer"] = {"size": buffer.size, "next": buffer._next, **buffer.fields()}
    del saved["replays"]
    save_checkpoint(checkpoint, "run", saved)
    previous(checkpoint).unlink()
    shutil.rmtree(replay_folder(checkpoint))
    resume(out, progress=False)
    assert_same_run(tmp_path / "whole", out)


def test_no_usable_checkpoint_is_refused_and_nothing_changes(tmp_path, monkeypatch):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train_until_stopped(monkeypatch, recipe, tmp_path, 3, max_steps=700, progress=False)
    for path in (tmp_path / "checkpoints" / "run.pt", previous(tmp_path / "checkpoints" / "run.pt")):
        path.write_bytes(b"\0" * 64)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(CheckpointError, match="no usable checkpoint is left"):
        resume(tmp_path, progress=False)
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_divergence_stops_naming_layer_phase_and_step_and_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    import torch

    from layered.learners.td3 import TD3

    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    original, calls = TD3.update, []

    def update(self):
        calls.append(1)
        losses = original(self)
        return {"critic": torch.tensor(float("nan"))} if len(calls) == 400 else losses

    monkeypatch.setattr(TD3, "update", update)
    # The 400th update is at step 325 of phase 1; losses are read back at the next evaluation or
    # checkpoint, here the episode end at step 400, before anything of that checkpoint is written.
    with pytest.raises(Diverged, match="layer 'fast' met a non-finite loss in phase 1 at step 400") as diverged:
        train(recipe, tmp_path, max_steps=700, progress=False)
    way_on = ("the last checkpoint is intact: continue from it with a lower learning rate, "
              f"`layered resume {tmp_path} --set layers.fast.learner.lr=0.0001`")
    assert str(diverged.value).endswith(way_on)
    monkeypatch.undo()
    for settings, why in ((["env.id=Hopper-v5"], "not env.id"), (["layers.fast.learner.hidden=[8]"], "does not fit"),
                          (["layers.fast.learner.lr=3e-4"], "changes nothing"),
                          (["layers.fast.learner.lr=1e-4", "env.workers=2", "env.wait=spin"],
                           "so env.wait and env.workers change nothing in it")):
        with pytest.raises(RunDirError, match=why):
            resume(tmp_path, progress=False, settings=settings)
    resume(tmp_path, progress=False, settings=["layers.fast.learner.lr=1e-4"])  # from the last checkpoint
    info = read_run_info(tmp_path)
    assert [(c["phase"], c["step"], c["set"], c["differences"]) for c in info.changes] == [
        (1, 200, ["layers.fast.learner.lr=1e-4"], ["layers[1].learner.lr: 0.0003 -> 0.0001"])]
    assert load_recipe(tmp_path / "recipe.toml").learner_config(1).lr == 1e-4
    fast = load_checkpoint(tmp_path / "checkpoints" / "fast.pt", "fast")
    assert {g["lr"] for g in fast["actor_opt"]["param_groups"] + fast["critic_opt"]["param_groups"]} == {1e-4}


def test_a_divergence_before_the_first_checkpoint_says_to_train_again(tmp_path, monkeypatch):
    from layered.learners.td3 import TD3

    monkeypatch.setattr(TD3, "act", lambda self, obs, explore: np.full(self.action_space.shape, np.nan, np.float32))
    with pytest.raises(Diverged, match="no checkpoint was taken before it: train again with --force and a lower "
                       r"learning rate \(layers\.slow\.learner\.lr=0\.0001\)"):
        train(load_recipe(PENDULUM / "tla-c.toml", [*TINY, "train.warmup=0"]), tmp_path, max_steps=700, progress=False)


def layered(*args, **kwargs):
    return subprocess.Popen([sys.executable, "-m", "layered.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


CLI_RUN = [PENDULUM / "tla-c.toml", *TINY, "--steps", 1500, "--threads", 1]


def writing(run_dir: Path) -> bool:
    """Whether a checkpoint write is under way (its temporary file exists)."""
    return bool(list((run_dir / "checkpoints").glob(".run.pt.*")))


def test_killed_with_sigkill_at_random_moments_and_resumed_ends_byte_identical(tmp_path):
    """The promise: SIGKILL at random moments between checkpoints, and once as soon as a checkpoint write is
    under way (the write may finish first: whether the kill landed mid-write is printed, not asserted);
    resume each time; the same files as a run never killed."""
    whole, began = tmp_path / "whole", time.monotonic()
    assert layered("train", *CLI_RUN, "--out", whole).wait() == 0
    interval = (time.monotonic() - began) * 150 / 1500  # at most one checkpoint's time (eval.every) here
    out, rng = tmp_path / "killed", random.Random(7)
    proc, kills, mid_write = layered("train", *CLI_RUN, "--out", out), 0, False
    for k in range(4):
        if k == 1:  # as soon as a checkpoint is being written
            ready = partial(writing, out)
        else:
            ready = between_checkpoints(out / "checkpoints" / "run.pt", interval, rng)
        if not kill_when(proc, ready, timeout=30.0 + 10 * interval):
            break
        kills += 1
        mid_write |= k == 1 and ready()
        started = (out / "run.json").exists()  # killed before it wrote anything: the retry is the same train
        proc = layered("resume", out, "--threads", 1) if started else layered("train", *CLI_RUN, "--out", out)
    _, err = proc.communicate()
    assert proc.returncode == 0, err
    assert kills == 4, "the run finished before it was killed four times; lengthen it"
    assert_same_run(whole, out)
    print(f"killed {kills} times, once mid-write: {mid_write}")


def test_sigint_and_sigterm_stop_cleanly_with_a_checkpoint_and_one_line(tmp_path):
    whole = tmp_path / "whole"
    assert layered("train", *CLI_RUN, "--out", whole).wait() == 0
    out = tmp_path / "stopped"
    for signum, code, command in ((signal.SIGINT, 130, ("train", *CLI_RUN, "--out", out)),
                                  (signal.SIGTERM, 143, ("resume", out, "--threads", 1))):
        checkpoint = out / "checkpoints" / "run.pt"
        before = checkpoint.stat().st_mtime_ns if checkpoint.exists() else None
        proc = layered(*command)
        while (not checkpoint.exists() or checkpoint.stat().st_mtime_ns == before) and proc.poll() is None:
            time.sleep(0.01)  # until this process has written a checkpoint of its own
        time.sleep(0.3)
        os.kill(proc.pid, signum)
        _, err = proc.communicate()
        assert proc.returncode == code, err
        assert "Traceback" not in err and f"continue with: layered resume {out}" in err.splitlines()[-1]
    assert layered("resume", out, "--threads", 1).wait() == 0
    assert_same_run(whole, out)


def test_train_into_a_stopped_run_says_how_to_resume_and_force_starts_over(tmp_path):
    out = tmp_path / "run"
    proc = layered("train", *CLI_RUN, "--out", out)
    assert kill_when(proc, (out / "checkpoints" / "run.pt").exists, timeout=120.0), "it finished before a checkpoint"
    assert (out / "checkpoints" / "run.pt").exists()
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    proc = layered("train", *CLI_RUN, "--out", out)
    _, err = proc.communicate()
    assert proc.returncode == 2 and f"layered resume {out}" in err and len(err.strip().splitlines()) == 1
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before
    proc = layered("train", *CLI_RUN, "train.seed=1", "--out", out, "--force")
    assert proc.wait() == 0 and load_recipe(out / "recipe.toml").train.seed == 1


def _damage(path: Path, rng: random.Random) -> None:
    """Overwrite 64 bytes at a random offset inside a checkpoint, its size unchanged."""
    data = bytearray(path.read_bytes())
    at = rng.randrange(len(data) - 64)
    data[at:at + 64] = bytes(rng.randrange(256) for _ in range(64))
    path.write_bytes(bytes(data))


def _intact(path: Path) -> bool:
    try:
        load_checkpoint(path, "run")
        return True
    except (CheckpointError, FileNotFoundError):
        return False


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_twenty_random_faults_kill_damage_and_contention_end_byte_identical(tmp_path):
    """20 cycles, each of a fault picked at random: SIGKILL at a random moment, SIGKILL mid checkpoint
    write, bytes damaged in the newest checkpoint while nothing runs (the previous one is then used),
    or a second writer started while one runs (refused in one line, the first goes on); then the
    run is finished and compared with one never disturbed."""
    run = [*CLI_RUN[:-4], "--steps", 12000, "--threads", 1]  # long enough for 20 faults
    whole, began = tmp_path / "whole", time.monotonic()
    assert layered("train", *run, "--out", whole).wait() == 0
    interval = (time.monotonic() - began) * 150 / 12000  # at most one checkpoint's time (eval.every) here
    out, rng = tmp_path / "faults", random.Random(11)

    def start() -> subprocess.Popen:
        return layered("resume", out, "--threads", 1) if (out / "run.json").exists() else \
            layered("train", *run, "--out", out)

    faults = []
    for _ in range(20):
        fault = rng.choice(["kill", "kill mid-write", "damage", "second writer"])
        if fault == "damage":
            checkpoint = out / "checkpoints" / "run.pt"
            if _intact(checkpoint) and _intact(previous(checkpoint)):  # one intact checkpoint is kept
                _damage(checkpoint, rng)
                faults.append(fault)
            continue
        proc = start()
        if fault == "second writer":
            deadline = time.monotonic() + 30
            while writer(out) is None and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            second = layered("resume", out, "--threads", 1)
            _, err = second.communicate(timeout=60)
            if proc.poll() is None:  # the first still runs: the second was refused in one line
                errors = [line for line in err.splitlines() if line.startswith("layered:")]
                assert second.returncode == 2 and len(errors) == 1 and "is being written by" in errors[0], err
                faults.append(fault)
        ready = partial(writing, out) if fault == "kill mid-write" else \
            between_checkpoints(out / "checkpoints" / "run.pt", interval, rng)
        if kill_when(proc, ready, timeout=30.0 + 10 * interval):
            faults.append(fault)
        else:
            break  # the run finished early: too few faults, which the count below catches
    proc = start() if not (out / "results.json").exists() else None
    if proc is not None:
        _, err = proc.communicate()
        assert proc.returncode == 0, err
    assert_same_run(whole, out)
    print(f"faults: {faults}")
    assert len(faults) >= 10


@pytest.mark.parametrize("seeds", [[], ["--seeds", "0,1"]], ids=["single", "group"])
@pytest.mark.parametrize("phase", [0, 1])
def test_a_signal_while_a_phase_ends_says_what_follows(seeds, phase, tmp_path, monkeypatch, capsys):
    """SIGINT while a phase's end evaluations run: after the first phase the run stops at a checkpoint, as it
    says; after the last no step is left, so it says the run finishes, and the run does (exit 0, results)."""
    def signalled(inner):
        def wrapped(*args):
            result = args[-1]  # a single run's PhaseResult, or a group's list of them
            if (result[0] if isinstance(result, list) else result).index == phase:
                os.kill(os.getpid(), signal.SIGINT)  # handled at once, in this thread
            return inner(*args)
        return wrapped

    monkeypatch.setattr(trainer_module, "_finish_phase", signalled(trainer_module._finish_phase))
    monkeypatch.setattr(group_module.Group, "_finish_phase", signalled(group_module.Group._finish_phase))
    out = tmp_path / "run"
    code = main(["train", str(PENDULUM / "tla-c.toml"), *seeds, "--steps", "300", *TINY, "--out", str(out)])
    err = capsys.readouterr().err
    results = out / ("seed0" if seeds else "") / "results.json"
    if phase == 0:
        assert code == 130 and "to save a checkpoint (signal again to stop at once)" in err
        assert f"layered resume {out}" in err and not results.exists()
    else:
        assert code == 0 and "SIGINT: no step is left: finishing the last evaluations and writing the results" in err
        assert "to save a checkpoint" not in err and results.exists()


@pytest.mark.parametrize("seeds", [[], ["--seeds", "0,1"]], ids=["single", "group"])
def test_resume_and_eval_compute_with_the_threads_the_run_trained_with(seeds, tmp_path):
    """An evaluation's products sum in an order that depends on torch's threads, and so do its numbers' last digits:
    without --threads, resuming and evaluating take those the run trained with (run.json); --threads still rules."""
    import torch

    out, before = tmp_path / "run", torch.get_num_threads()
    try:
        assert main(["train", str(PENDULUM / "td3.toml"), *seeds, "--steps", "200", *TINY, "--threads", "1",
                     "--out", str(out)]) == 0
        assert read_run_info(out / "seed0" if seeds else out).threads == 1
        for command in (["resume", str(out)], ["eval", str(out), "--episodes", "1"]):
            torch.set_num_threads(2)
            assert main(command) == 0 and torch.get_num_threads() == 1
            assert main([*command, "--threads", "2"]) == 0 and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
