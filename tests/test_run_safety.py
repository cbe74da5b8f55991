"""Runs nothing can corrupt: one writer per run directory, checkpoints verified by a checksum, and a
--force that deletes nothing it may not."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from layered.checkpoint import CheckpointError, load_checkpoint, load_latest, save_checkpoint
from layered.cli import main
from layered.rundir import RunDirError, RunInfo, prepare_run_dir, writer, writing

STATE = {"w": torch.arange(12.0).reshape(3, 4), "step": 7}


def test_a_checkpoint_damaged_anywhere_is_refused(tmp_path):
    path = tmp_path / "layer.pt"
    save_checkpoint(path, "fast", STATE)
    good = path.read_bytes()
    assert torch.equal(load_checkpoint(path, "fast")["w"], STATE["w"])
    for offset in np.random.default_rng(0).integers(0, len(good), 64):
        damaged = bytearray(good)
        damaged[offset] ^= 0xA5
        path.write_bytes(bytes(damaged))
        with pytest.raises(CheckpointError, match=r"damaged|not a checkpoint|not a readable"):
            load_checkpoint(path, "fast")


def test_a_damaged_newest_checkpoint_gives_way_to_the_previous_one_and_two_are_refused(tmp_path, capsys):
    path = tmp_path / "run.pt"
    save_checkpoint(path, "run", {"step": 1}, keep_previous=True)
    save_checkpoint(path, "run", {"step": 2}, keep_previous=True)
    content = bytearray(path.read_bytes())
    content[len(content) // 2] ^= 0xFF
    path.write_bytes(bytes(content))
    assert load_latest(path, "run") == {"step": 1}
    assert "damaged (its checksum does not match its content); using the previous checkpoint" in capsys.readouterr().err
    previous = path.with_name("run.prev.pt")
    previous.write_bytes(previous.read_bytes()[:-10])
    with pytest.raises(CheckpointError, match="no usable checkpoint is left"):
        load_latest(path, "run")


def test_a_file_that_both_checkpoints_name_is_named_once_when_neither_can_be_used(tmp_path):
    path = tmp_path / "run.pt"
    save_checkpoint(path, "run", STATE)
    save_checkpoint(path, "run", STATE, keep_previous=True)

    def check(state):
        raise CheckpointError("replay/segment-1.pt: missing")  # (a segment both checkpoints hold)

    with pytest.raises(CheckpointError) as refused:
        load_latest(path, "run", check)
    assert str(refused.value) == "replay/segment-1.pt: missing; no usable checkpoint is left"


def test_one_writer_per_run_directory(tmp_path):
    with writing(tmp_path / "run"):
        assert writer(tmp_path / "run") is None  # no other writer
        with pytest.raises(RunDirError, match=f"is being written by process {os.getpid()}"), writing(tmp_path / "run"):
            pass
    assert writer(tmp_path / "run") is None


def hold_lock(run_dir):
    """A process that holds the run directory's lock until it is killed."""
    script = ("import sys, time; from pathlib import Path; from layered.rundir import writing\n"
              "with writing(Path(sys.argv[1])):\n    print('held', flush=True); time.sleep(120)")
    holder = subprocess.Popen([sys.executable, "-c", script, str(run_dir)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_a_second_writer_is_refused_in_one_line_and_a_killed_writer_leaves_no_lock(tmp_path, capsys):
    run = tmp_path / "run"
    prepare_run_dir(run, "[env]\nid = 'Pendulum-v1'\n[[layers]]\nname = 'fast'\nperiod = 1\n",
                    RunInfo("run", None), resume=False)
    holder = hold_lock(run)
    try:
        assert main(["resume", str(run)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 2 and f"is being written by process {holder.pid}" in err[1]  # "resuming ...", then why not
        assert main(["train", "pendulum/td3.toml", "--out", str(run)]) == 2
        assert f"is being written by process {holder.pid}" in capsys.readouterr().err
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    deadline = time.monotonic() + 10
    while writer(run) is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert writer(run) is None  # the kernel released it with the process


def test_force_clears_a_run_only_once_the_command_is_taken(tmp_path, capsys):
    run = tmp_path / "run"
    tiny = ["learner.hidden=[16]", "learner.batch_size=16", "train.warmup=20", "eval.every=100", "eval.episodes=1",
            "eval.fresh_episodes=1", "--steps", "100", "--threads", "1", "--out", str(run)]
    assert main(["train", "pendulum/td3.toml", *tiny]) == 0
    before = {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != ".lock"}
    capsys.readouterr()
    assert main(["train", "pendulum/td3.toml", *tiny, "--force", f"layers.fast.weights={tmp_path / 'nope.pt'}"]) == 2
    assert "no checkpoint for layer 'fast'" in capsys.readouterr().err
    assert {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != ".lock"} == before
    assert main(["train", "pendulum/td3.toml", *tiny, "--force", "train.seed=1"]) == 0  # taken: started over
    assert json.loads((run / "run.json").read_text())["label"] and "seed = 1" in (run / "recipe.toml").read_text()


def test_what_a_killed_write_left_is_the_runs_own_and_its_next_writer_removes_it(tmp_path):
    from layered.checkpoint import unfinished_write

    assert unfinished_write(".recipe.toml.k3j_h5g6") == "recipe.toml" and unfinished_write(".lock") is None
    assert unfinished_write(".notes.txt") is None and unfinished_write("recipe.toml.k3j4h5g6") is None
    run = tmp_path / "run"
    run.mkdir()
    (run / ".recipe.toml.k3j4h5g6").write_text("[env")  # killed while writing the run's first file
    tiny = ["learner.hidden=[16]", "learner.batch_size=16", "train.warmup=20", "eval.every=100", "eval.episodes=1",
            "eval.fresh_episodes=1", "--steps", "100", "--threads", "1", "--out", str(run)]
    assert main(["train", "pendulum/td3.toml", *tiny]) == 0  # a run that wrote nothing starts without asking
    assert not (run / ".recipe.toml.k3j4h5g6").exists()
    (run / "checkpoints" / ".fast.best.pt.0a1b2c3d").write_bytes(b"half")
    (run / ".results.json.0a1b2c3d").write_text("{")
    (run / ".notes.abcdefgh").write_text("mine")  # (a file of the user's that only looks like one)
    assert main(["train", "pendulum/td3.toml", *tiny, "--force"]) == 2  # the user's file is not the run's
    (run / ".notes.abcdefgh").unlink()
    assert main(["train", "pendulum/td3.toml", *tiny, "--force"]) == 0
    assert not list(run.glob(".*.*")) and not list((run / "checkpoints").glob(".*"))


def test_a_full_disk_and_a_cut_log_say_what_happened_and_the_way_on(tmp_path, monkeypatch, capsys):
    import errno


    import layered.runs

    run = tmp_path / "run"
    tiny = ["learner.hidden=[16]", "learner.batch_size=16", "train.warmup=20", "eval.every=100", "eval.episodes=1",
            "eval.fresh_episodes=1", "train.checkpoint_every=100", "--steps", "400", "--threads", "1",
            "--out", str(run)]

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")  # (as a write in a thread says it: no file named)

    monkeypatch.setattr(layered.runs, "write_results", full)
    assert main(["train", "pendulum/td3.toml", *tiny]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"layered: error: No space left on device (writing {run}); continue from the last checkpoint with: "
        f"layered resume {run}")
    monkeypatch.undo()
    (run / "metrics.csv").write_text("step\n")  # cut below what the last checkpoint recorded
    assert main(["resume", str(run)]) == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said.startswith(f"layered: error: {run / 'metrics.csv'} is shorter than the ") and "--force" in said


def test_a_finished_runs_damaged_results_are_written_again_by_resume(tmp_path, capsys):
    run = tmp_path / "run"
    tiny = ["learner.hidden=[16]", "learner.batch_size=16", "train.warmup=20", "eval.every=100", "eval.episodes=1",
            "eval.fresh_episodes=1", "--steps", "200", "--threads", "1", "--out", str(run)]
    assert main(["train", "pendulum/td3.toml", *tiny]) == 0
    whole = (run / "results.json").read_bytes()
    (run / "results.json").write_bytes(whole[:100])  # damaged (cut short)
    capsys.readouterr()
    assert main(["resume", str(run)]) == 0
    assert "results.json is damaged; writing the run's results again" in capsys.readouterr().err
    assert (run / "results.json").read_bytes() == whole
    assert main(["resume", str(run)]) == 0 and "has finished; nothing to resume" in capsys.readouterr().err
    # what a stopped run would have refused or changed is said of a finished one too
    assert main(["resume", str(run), "--steps", "300"]) == 2
    assert "it was started with --steps 200, not --steps 300" in capsys.readouterr().err
    assert main(["resume", str(run), "--set", "layers.fast.learner.lr=1e-4"]) == 2
    assert "a finished one continues no further" in capsys.readouterr().err


def test_force_deletes_nothing_in_a_directory_that_holds_files_of_another_kind(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "results.json").write_text(json.dumps({"phases": []}))
    (run / "checkpoints" / "fast.pt").write_bytes(b"weights")
    (run / "notes.txt").write_text("mine")
    assert main(["train", "pendulum/td3.toml", "--out", str(run), "--force"]) == 2
    assert "notes.txt" in capsys.readouterr().err
    assert (run / "results.json").exists() and (run / "checkpoints" / "fast.pt").exists()
    assert (run / "notes.txt").read_text() == "mine"
