"""A group of seeds survives being stopped or killed: checkpointed at any step, mid-episode in every seed,
it resumes to the very files of a group that never stopped."""

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

import pytest
import torch
from conftest import assert_same_run, between_checkpoints, kill_when, stop_at

from layered.rundir import RunDirError
from layered.cli import main
import layered.group as group_module
from layered.group import Group, resume_group
from layered.group_state import GROUP_CHECKPOINT, group_dir
from layered.best_journal import best_folder
from layered.checkpoint import load_checkpoint, previous, save_checkpoint
from layered.replay_journal import replay_folder

ROOT = Path(__file__).resolve().parent.parent
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=40", "eval.every=150", "eval.episodes=1",
        "eval.fresh_episodes=1"]


def assert_same_group(a: Path, b: Path, seeds) -> None:
    for seed in seeds:
        assert_same_run(a / f"seed{seed}", b / f"seed{seed}")
    assert not (b / GROUP_CHECKPOINT).exists(), "a finished group keeps no checkpoint"


@pytest.mark.parametrize("recipe, overrides, steps, moments", [
    ("pendulum/tla-c.toml", [], 300, [(0, 137), (1, 1), (1, 299)]),  # mid-episode; a phase's first and last step
    ("inverted-double-pendulum/tla-realtime.toml", [], 300, [(0, 101), (1, 151)]),  # delays in flight, early ends
    ("pendulum/tla-o.toml", ["train.order=joint", "train.warmup=100"], 300, [(0, 177)]),  # a gate committing
    ("dmc-cartpole-balance/td3.toml", [], 200, [(0, 123)]),  # a dm_control task
    ("pendulum/tla-joint.toml", ["layers.slow.warmup=20"], 400, [(0, 157)]),  # the learned gate (td3-gate)
    ("pendulum/temporl.toml", ["layers.fast.period=2"], 400, [(0, 155)]),  # a repeat under way (temporl)
    pytest.param("pendulum/tla-c.toml", ["learner.device=cuda", "learner.compile=cudagraphs"], 300,
                 [(0, 137), (1, 151)], marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU"),
                 id="cudagraphs"),  # updates captured, then eager again after each resume until captured anew
    pytest.param("pendulum/tla-c.toml", ["learner.device=cuda", "learner.compile=cudagraphs", "learner.precision=tf32"],
                 300, [(0, 137)], marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU"),
                 id="cudagraphs-tf32"),  # the TF32 products captured in the graphs
])
def test_a_group_stopped_mid_episode_resumes_to_the_same_files(recipe, overrides, steps, moments, tmp_path,
                                                               monkeypatch):
    command = ["train", str(ROOT / "recipes" / recipe), "--seeds", "0,3", "--steps", str(steps), *TINY, *overrides]
    assert main([*command, "--out", str(tmp_path / "whole")]) == 0
    out = tmp_path / "stopped"
    stop_at(monkeypatch, moments)
    assert main([*command, "--out", str(out)]) == 130
    for _ in moments[1:]:
        assert (out / GROUP_CHECKPOINT).exists()
        assert main(["resume", str(out / "seed3")]) == 130  # a seed's directory resumes its group
    monkeypatch.undo()
    assert main(["resume", str(out)]) == 0
    assert_same_group(tmp_path / "whole", out, (0, 3))


@pytest.mark.parametrize("wait", ["sleep", "spin"])
def test_a_group_stepping_its_environments_in_workers_and_threads_writes_the_files_of_one_stepping_them_here(
        tmp_path, monkeypatch, wait):
    """Also when it is resumed in fewer workers waiting the other way (`--set`, as on a machine with other cores):
    snapshots taken in two workers are restored in one."""
    command = ["train", str(ROOT / "recipes/inverted-double-pendulum/tla-realtime.toml"), "--seeds", "0,3,4",
               "--steps", "300", *TINY]
    assert main([*command, "env.workers=0", "env.threads=0", "--out", str(tmp_path / "here")]) == 0
    out = tmp_path / "workers"
    stop_at(monkeypatch, [(0, 101), (1, 151)])  # snapshots taken in the workers, restored in new ones
    assert main([*command, "env.workers=2", "env.threads=2", f"env.wait={wait}", "--out", str(out)]) == 130
    other = {"sleep": "spin", "spin": "sleep"}[wait]
    assert main(["resume", str(out), "--set", "env.workers=1", "--set", f"env.wait={other}"]) == 130
    monkeypatch.undo()
    assert main(["resume", str(out)]) == 0
    assert_same_group(tmp_path / "here", out, (0, 3, 4))
    changes = json.loads((out / "seed3" / "run.json").read_text())["changes"]
    assert [(c["phase"], c["step"], c["differences"]) for c in changes] == [
        (0, 101, [f"env.wait: {wait!r} -> {other!r}", "env.workers: 2 -> 1"])]
    assert "workers = 1" in (out / "seed3" / "recipe.toml").read_text()


def stopped_beside_whole(tmp_path, monkeypatch, moment):
    """A TLA-C group of seeds 0 and 3 trained whole, and the same group stopped at `moment` (checkpoints every 100
    steps); the stopped group's directory."""
    command = ["train", str(ROOT / "recipes/pendulum/tla-c.toml"), "--seeds", "0,3", "--steps", "300", *TINY,
               "train.checkpoint_every=100"]
    assert main([*command, "--out", str(tmp_path / "whole")]) == 0
    out = tmp_path / "stopped"
    stop_at(monkeypatch, [moment])
    assert main([*command, "--out", str(out)]) == 130
    monkeypatch.undo()
    return out


def assert_resumes_from_the_one_before(tmp_path, out, damaged, capsys, at):
    """With the file `damaged` cut short, the stopped group in `out` resumes from its previous checkpoint (its
    line says it continues `at`) to the files of the whole group."""
    damaged.write_bytes(damaged.read_bytes()[:-10])
    capsys.readouterr()
    assert main(["resume", str(out)]) == 0
    err = capsys.readouterr().err
    assert "damaged" in err and "using the previous checkpoint group.prev.pt" in err
    assert f"continues from its checkpoint in {at}" in err
    assert_same_group(tmp_path / "whole", out, (0, 3))


def test_a_group_whose_newest_replay_segment_is_damaged_resumes_from_the_checkpoint_before(tmp_path, monkeypatch,
                                                                                           capsys):
    out = stopped_beside_whole(tmp_path, monkeypatch, (0, 250))  # checkpoints at steps 100, 200 and 250
    segments = sorted(replay_folder(out / GROUP_CHECKPOINT).glob("slow.td3.*.pt"))
    assert len(segments) == 3, "one per checkpoint, each of the rows stored since the one before"
    assert_resumes_from_the_one_before(tmp_path, out, segments[-1], capsys, "phase 0 at step 200")
    assert not replay_folder(out / GROUP_CHECKPOINT).exists(), "a finished group keeps no replay segments"


def test_a_group_whose_newest_best_weights_are_damaged_resumes_from_the_checkpoint_before(tmp_path, monkeypatch,
                                                                                           capsys):
    out = stopped_beside_whole(tmp_path, monkeypatch, (1, 50))  # phase 1's first checkpoint: phase 1's best, new files
    newest = load_checkpoint(out / GROUP_CHECKPOINT, "group")["best"]
    before = load_checkpoint(previous(out / GROUP_CHECKPOINT), "group")["best"]
    assert not {a["file"] for a in newest["files"]} & {a["file"] for a in before["files"]}
    damaged = best_folder(out / GROUP_CHECKPOINT) / newest["files"][1]["file"]
    assert_resumes_from_the_one_before(tmp_path, out, damaged, capsys, "phase 0")
    assert not best_folder(out / GROUP_CHECKPOINT).exists(), "a finished group keeps no best weights"


def test_a_group_checkpoint_holding_its_best_weights_inline_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    command = ["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "0,1", "--steps", "200", *TINY,
               "train.checkpoint_every=50", "--out", str(tmp_path / "g")]
    stop_at(monkeypatch, [(0, 120)])
    assert main(command) == 130
    for path in (tmp_path / "g" / GROUP_CHECKPOINT, previous(tmp_path / "g" / GROUP_CHECKPOINT)):
        state = load_checkpoint(path, "group")
        state["best"] = [{}, {}]  # as the group checkpoints of a development version held them
        save_checkpoint(path, "group", state)
    capsys.readouterr()
    assert main(["resume", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("layered: error")]
    assert len(errors) == 1 and "start the group again with --force" in errors[0]


def test_a_stopped_group_is_refused_a_new_start_and_other_steps_and_force_starts_over(tmp_path, monkeypatch, capsys):
    command = ["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "2", "--steps", "200", *TINY,
               "--out", str(tmp_path / "g")]
    stop_at(monkeypatch, [(0, 50)])
    assert main(command) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(f"continue with: layered resume {tmp_path / 'g'}")
    monkeypatch.undo()
    assert main(command) == 2
    assert "holds a stopped group; continue it with `layered resume" in capsys.readouterr().err
    with pytest.raises(RunDirError, match="--steps 200, not --steps 100"):
        resume_group(tmp_path / "g", max_steps=100)
    assert main(["resume", str(tmp_path / "g"), "--set", "env.id=Hopper-v5"]) == 2
    assert group_dir(tmp_path / "g") == group_dir(tmp_path / "g" / "seed1") == tmp_path / "g"
    stopped = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.name != ".lock")
    capsys.readouterr()
    # --force clears nothing for a command refused after it: start weights that are not there
    assert main([*command, "--force", f"layers.fast.weights={tmp_path / 'nope.pt'}"]) == 2
    assert "layers[0].weights" in capsys.readouterr().err
    # nor a single run in a seed's place, which would leave the other seeds unfinishable
    assert main(["train", str(ROOT / "recipes/pendulum/td3.toml"), *TINY, "--out", str(tmp_path / "g" / "seed1"),
                 "--force"]) == 2
    assert "holds a seed of the group of seeds [0, 1]" in capsys.readouterr().err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.name != ".lock") == stopped
    recipe = tmp_path / "g" / "seed1" / "recipe.toml"
    kept = recipe.read_text()
    recipe.write_text(kept.replace("seed = 1", "seed = 5"))
    assert main(["resume", str(tmp_path / "g")]) == 2
    assert "train.seed is 5, but the group trained seed 1 there" in capsys.readouterr().err
    recipe.write_text(kept.replace("warmup = 40", "warmup = 30"))
    assert main(["resume", str(tmp_path / "g")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(
        "the recipe of seeds [1] differs from the one the group's checkpoint was taken with (train.warmup: 40 -> 30)")
    recipe.write_text(kept)
    assert main([*command, "--force"]) == 0
    assert not (tmp_path / "g" / GROUP_CHECKPOINT).exists()
    assert main(["resume", str(tmp_path / "g")]) == 0
    assert "has finished; nothing to resume" in capsys.readouterr().err


def test_a_checkpoint_that_cannot_be_written_is_the_error_and_the_one_before_resumes(tmp_path, monkeypatch, capsys):
    """Checkpoints are written beside training (tests run one torch thread on several cores): a write that fails,
    here the stop's, is named where the group would have said "checkpoint saved", and the group resumes from
    the checkpoint before it to the files of a group never stopped."""
    command = ["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "0,1", "--steps", "300", *TINY,
               "train.checkpoint_every=50"]
    assert main([*command, "--out", str(tmp_path / "whole")]) == 0
    write = group_module.save_group

    def full_disk(directory, snapshot):
        if snapshot["loop"]["step"] == 120:
            raise OSError(28, "No space left on device")
        write(directory, snapshot)

    monkeypatch.setattr(group_module, "save_group", full_disk)
    stop_at(monkeypatch, [(0, 120)])
    out = tmp_path / "stopped"
    assert main([*command, "--out", str(out)]) != 130
    err = capsys.readouterr().err
    assert "No space left on device" in err and "checkpoint saved" not in err
    monkeypatch.undo()
    assert main(["resume", str(out)]) == 0
    assert "continues from its checkpoint in phase 0 at step 100" in capsys.readouterr().err
    assert_same_group(tmp_path / "whole", out, (0, 1))


def test_a_sweep_of_groups_resumes_a_stopped_group(tmp_path, monkeypatch):
    recipe = str(ROOT / "recipes/pendulum/td3.toml")
    sweep = ["sweep", recipe, "--seeds", "2", "--steps", "200", "--vectorize", "--jobs", "1", "--threads", "1", *TINY]
    assert main([*sweep, "--out", str(tmp_path / "whole")]) == 0
    setup = next((tmp_path / "whole").rglob("seed0")).parent.relative_to(tmp_path / "whole")
    out = tmp_path / "stopped"
    stop_at(monkeypatch, [(0, 77)])  # the group the sweep would train, stopped by a signal
    assert main(["train", recipe, "--seeds", "2", "--steps", "200", *TINY, "--out", str(out / setup)]) == 130
    monkeypatch.undo()
    assert main([*sweep, "--out", str(out)]) == 0
    assert "continues from its checkpoint in phase 0 at step 77" in (out / setup / "group.log").read_text()
    assert_same_group(tmp_path / "whole" / setup, out / setup, (0, 1))


def layered(*args):
    return subprocess.Popen([sys.executable, "-m", "layered.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def writing(directory: Path) -> bool:
    """Whether a checkpoint of the group is being written (its temporary file exists)."""
    return bool(list(directory.glob(f".{GROUP_CHECKPOINT}.*")))


def test_a_group_killed_at_random_moments_and_mid_checkpoint_resumes_byte_identical(tmp_path):
    """SIGKILL at random moments between checkpoints and once as soon as a checkpoint write is under way;
    resumed each time, the group ends with the files of one never killed; SIGINT and SIGTERM then stop it in
    one line."""
    steps, every = 600, 40
    run = ["train", ROOT / "recipes/inverted-double-pendulum/tla-realtime.toml", "--seeds", "0,1", "--steps", steps,
           *TINY, f"train.checkpoint_every={every}", "--threads", 1]
    whole, out = tmp_path / "whole", tmp_path / "killed"
    began = time.monotonic()
    assert layered(*run, "--out", whole).wait() == 0
    interval = (time.monotonic() - began) * every / steps  # at most one checkpoint's time on this machine
    proc, rng, kills = layered(*run, "--out", out), random.Random(3), 0
    for k in range(4):
        ready = partial(writing, out) if k == 1 else between_checkpoints(out / GROUP_CHECKPOINT, interval, rng)
        if not kill_when(proc, ready, timeout=30.0 + 10 * interval):
            break
        kills += 1
        started = (out / "seed0" / "run.json").exists()
        proc = layered("resume", out, "--threads", 1) if started else layered(*run, "--out", out)
    signalled = 0
    for signum, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        checkpoint = out / GROUP_CHECKPOINT
        before = checkpoint.stat().st_mtime_ns if checkpoint.exists() else None
        while (not checkpoint.exists() or checkpoint.stat().st_mtime_ns == before) and proc.poll() is None:
            time.sleep(0.01)  # until this process has written a checkpoint of its own
        if proc.poll() is not None:
            break
        os.kill(proc.pid, signum)
        _, err = proc.communicate()
        assert proc.returncode == code, err
        assert "Traceback" not in err and err.strip().splitlines()[-1].endswith(f"layered resume {out}")
        signalled += 1
        proc = layered("resume", out, "--threads", 1)
    _, err = proc.communicate()
    assert proc.returncode == 0, err
    assert (kills, signalled) == (4, 2), "the group finished before it was killed and signalled; lengthen it"
    assert_same_group(whole, out, (0, 1))


def test_an_environment_that_cannot_be_checkpointed_is_refused_before_a_group_starts(remembering_env_id, tmp_path,
                                                                                       capsys):
    out = tmp_path / "g"
    assert main(["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "2", f"env.id={remembering_env_id}",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "env.id" in err[0] and "recent holds a deque" in err[0] and "layered sweep" in err[0]
    assert not out.exists()


def test_a_diverged_group_resumes_with_a_lower_learning_rate_recorded_in_every_seed(tmp_path, monkeypatch, capsys):
    """A non-finite loss stops the group, naming the way on: its last checkpoint, with `--set` a lower learning
    rate; what a run may not change, what changes nothing and what the networks cannot take are refused with
    nothing written; the change is recorded in each seed's run.json and recipe, and taken by the stacked
    learners (their weights end unlike the unchanged group's); a group stopped before its next checkpoint
    resumes from the one taken before the change."""
    from layered.cli import EXIT_DIVERGED
    from layered.learners.td3_group import TD3Group
    from layered.recipe import load_recipe
    from layered.rundir import read_run_info

    out = tmp_path / "g"
    command = ["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "0,1", "--steps", "300", *TINY,
               "train.checkpoint_every=50", "--out", str(out)]
    original, calls = TD3Group.update, []

    def update(self, rows=None):
        calls.append(1)
        losses = original(self, rows)
        if len(calls) == 150:  # (the update of step 190: read back at the checkpoint of step 200)
            losses["critic"] = (torch.full_like(losses["critic"][0], float("nan")), losses["critic"][1])
        return losses

    monkeypatch.setattr(TD3Group, "update", update)
    assert main(command) == EXIT_DIVERGED
    monkeypatch.undo()
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == ("layered: diverged: layer 'fast' met a non-finite loss in phase 0 at step 200 of a group; the last "
                   "checkpoint is intact: continue from it with a lower learning rate, "
                   f"`layered resume {out} --set layers.fast.learner.lr=0.0001`")
    untouched = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    for setting, why in (("env.id=Hopper-v5", "not env.id"), ("layers.fast.learner.lr=3e-4", "changes nothing"),
                         ("layers.fast.learner.hidden=[8]", "does not fit")):
        with pytest.raises(RunDirError, match=why):
            resume_group(out, progress=False, settings=[setting])
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == untouched, setting

    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    monkeypatch.setattr(Group, "train", lambda self, saved: (_ for _ in ()).throw(KeyboardInterrupt))
    # stopped at once with the change recorded, before a checkpoint of its own
    assert main(["resume", str(out), "--set", "layers.fast.learner.lr=1e-4"]) == 130
    monkeypatch.undo()
    assert main(["resume", str(out)]) == 0
    assert "continues from its checkpoint in phase 0 at step 150" in capsys.readouterr().err
    assert main(["resume", str(copy)]) == 0
    for seed in (0, 1):
        info = read_run_info(out / f"seed{seed}")
        assert [(c["phase"], c["step"], c["set"], c["differences"]) for c in info.changes] == [
            (0, 150, ["layers.fast.learner.lr=1e-4"], ["layers[0].learner.lr: 0.0003 -> 0.0001"])]
        assert load_recipe(out / f"seed{seed}" / "recipe.toml").learner_config(0).lr == 1e-4
        lowered, kept = (load_checkpoint(d / f"seed{seed}" / "checkpoints" / "fast.pt", "fast") for d in (out, copy))
        assert {g["lr"] for g in lowered["actor_opt"]["param_groups"]} == {1e-4}
        assert not torch.equal(lowered["actor"]["net.0.weight"], kept["actor"]["net.0.weight"])


def test_a_group_stopped_at_once_while_writing_its_results_says_how_to_resume_it(tmp_path, monkeypatch, capsys):
    """A second signal (here as the results are written, past the last step) stops a group at once: its last
    line names `layered resume` on the group's directory, and the group resumes from its checkpoint."""
    out = tmp_path / "g"

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(group_module, "write_results", interrupted)
    assert main(["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "0,1", "--steps", "200", *TINY,
                 "--out", str(out)]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"layered: stopped at once; continue from the last checkpoint with: layered resume {out}")
    monkeypatch.undo()
    assert main(["resume", str(out)]) == 0
    assert all((out / f"seed{seed}" / "results.json").exists() for seed in (0, 1))


def test_a_group_is_refused_a_directory_that_holds_another_group_or_a_run_of_its_own(tmp_path, capsys):
    """A directory holds one group: its resume, evaluation and report take the group its seeds' run.json name, so a
    second group's seeds beside them could be neither resumed nor evaluated; even --force leaves the others there."""
    train = ["train", str(ROOT / "recipes/pendulum/td3.toml"), "--steps", "100", *TINY]
    assert main([*train, "--seeds", "0-1", "--out", str(tmp_path / "g")]) == 0
    assert main([*train, "--out", str(tmp_path / "single")]) == 0
    assert main([*train, "--seed", "5", "--out", str(tmp_path / "runs" / "a")]) == 0
    for out, seeds, says in ((tmp_path / "g", "3-4", "holds seed0, seed1 of another group"),
                             (tmp_path / "single", "0-1", "holds a run of its own"),
                             (tmp_path / "runs", "0-1", "holds a of other runs")):
        capsys.readouterr()
        for force in ([], ["--force"]):
            assert main([*train, "--seeds", seeds, "--out", str(out), *force]) == 2
            assert says in capsys.readouterr().err
        assert not (out / "seed3").exists() and not (tmp_path / "single" / "seed0").exists()
    assert main([*train, "--seeds", "0-1", "--out", str(tmp_path / "g"), "--force"]) == 0  # the same group again


@pytest.mark.parametrize("seeds", [None, "0,1"], ids=["single run", "group"])
def test_a_signal_while_the_results_are_written_lets_them_finish(seeds, tmp_path, monkeypatch, capsys):
    """Past the last step no checkpoint could stop a run sooner: one signal as its results are written says so and
    the results are finished (exit 0); the handler used to be gone by then, and the run stopped at once."""
    import os
    import signal

    import layered.runs as runs_module

    module = runs_module if seeds is None else group_module
    original, sent = module.write_results, []

    def signalled(*args):
        if not sent:  # (once: a group writes each seed's)
            sent.append(os.kill(os.getpid(), signal.SIGINT))
        return original(*args)

    monkeypatch.setattr(module, "write_results", signalled)
    out = tmp_path / "run"
    seed = ["--seeds", seeds] if seeds else []
    assert main(["train", str(ROOT / "recipes/pendulum/td3.toml"), *seed, "--steps", "200", *TINY,
                 "--out", str(out)]) == 0
    assert "no step is left: finishing the last evaluations and writing the results" in capsys.readouterr().err
    assert all((run / "results.json").exists() for run in ([out] if seeds is None else [out / "seed0", out / "seed1"]))
