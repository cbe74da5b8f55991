"""Sweeps: every (recipe, seed) pair runs once in its own directory; finished runs are skipped."""

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
import tomli_w
from conftest import layered_here

from layered.cores import usable_cores
from layered.env_workers import worker_count
from layered.sweep import _init_worker, _one, plan, process_count, run_group, tasks

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
        "eval.every=100", "eval.episodes=1", "eval.fresh_episodes=2"]


def sweep(*args):
    command = [sys.executable, "-m", "layered.cli", "sweep", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True)


def test_sweep_runs_each_pair_in_parallel_then_skips_finished_runs(tmp_path):
    out = tmp_path / "sw"
    recipes = (PENDULUM / "td3.toml", PENDULUM / "tla-o.toml")
    args = (*recipes, *TINY, "--seeds", 2, "--jobs", 2, "--steps", 150, "--out", out)
    proc = sweep(*args)
    assert proc.returncode == 0, proc.stderr
    runs = sorted(p.parent.relative_to(out).as_posix() for p in out.rglob("results.json"))
    assert runs == ["pendulum/td3/seed0", "pendulum/td3/seed1", "pendulum/tla-o/seed0", "pendulum/tla-o/seed1"]
    assert "4 of 4 runs finished" in proc.stdout
    seeds = {(out / r / "recipe.toml").read_text().count("seed = 1") for r in runs}
    assert seeds == {0, 1}
    before = (out / "pendulum/tla-o/seed1/metrics.csv").read_text()
    again = layered_here("sweep", *args)  # (nothing to train: here, without a child's start)
    assert again.returncode == 0 and again.stdout.count("skipped") == 4
    assert (out / "pendulum/tla-o/seed1/metrics.csv").read_text() == before


def test_sweep_refuses_bad_recipes_and_foreign_run_directories(tmp_path):
    out = tmp_path / "sw"
    proc = layered_here("sweep", PENDULUM / "td3.toml", "train.warmup=-1", "--out", out)
    assert proc.returncode == 2 and "train.warmup" in proc.stderr and not out.exists()
    assert sweep(PENDULUM / "td3.toml", *TINY, "--seeds", 1, "--steps", 100, "--out", out).returncode == 0
    proc = layered_here("sweep", PENDULUM / "td3.toml", *TINY, "learner.lr=1e-3", "--seeds", 1, "--out", out)
    assert proc.returncode == 2 and "holds a different recipe (layers[0].learner.lr: 0.0003 -> 0.001;" in proc.stderr
    proc = layered_here("sweep", PENDULUM / "td3.toml", *TINY, "--seeds", 1, "--steps", 200, "--out", out)  # not reused
    assert proc.returncode == 2 and "this run was made with --steps 100, not --steps 200" in proc.stderr


def test_recipes_of_the_same_folder_and_name_get_run_directories_of_their_own(tmp_path):
    from layered.sweep import plan

    for place in ("a", "b"):
        (tmp_path / place / "pendulum").mkdir(parents=True)
        (tmp_path / place / "pendulum" / "td3.toml").write_text((PENDULUM / "td3.toml").read_text())
    recipes = [tmp_path / place / "pendulum" / "td3.toml" for place in ("a", "b")] + [PENDULUM / "tla-c.toml"]
    jobs = plan([*recipes, recipes[0]], 1, tmp_path / "out")  # the first one named twice: run once
    assert [job.out.relative_to(tmp_path / "out").as_posix() for job in jobs] == [
        "a/pendulum/td3/seed0", "b/pendulum/td3/seed0", "pendulum/tla-c/seed0"]
    assert [job.label for job in jobs] == ["a/pendulum/td3", "b/pendulum/td3", "pendulum/tla-c"]


def test_ray_backend_runs_the_same_jobs_resumes_a_stopped_one_and_gathers_the_same_run_directories(tmp_path,
                                                                                                   monkeypatch):
    """Seed 0 stopped at a checkpoint beforehand goes on from it as a Ray task, seed 1 trains from the start:
    both end with the files of a local sweep."""
    pytest.importorskip("ray", reason="the ray backend is the optional extra layered[ray]")
    from conftest import train_until_stopped

    from layered import load_recipe
    from layered.sweep import plan

    args = (PENDULUM / "td3.toml", *TINY, "--seeds", 2, "--steps", 450)
    local = sweep(*args, "--jobs", 2, "--out", tmp_path / "local")
    assert local.returncode == 0, local.stderr
    stopped = plan([PENDULUM / "td3.toml"], 2, tmp_path / "ray", TINY, 450)[0]
    train_until_stopped(monkeypatch, load_recipe(stopped.recipe), stopped.out, 1, max_steps=450, progress=False,
                        label=stopped.label)
    remote = sweep(*args, "--backend", "ray", "--out", tmp_path / "ray")
    assert remote.returncode == 0, remote.stderr
    log = (stopped.out / "train.log").read_text()  # the Ray task's own progress lines, one per evaluation
    assert "step 450/450" in log and "step 0/450" not in log  # it went on from the checkpoint
    for seed in (0, 1):
        run = Path("pendulum/td3") / f"seed{seed}"
        for name in ("metrics.csv", "episodes.csv", "results.json", "recipe.toml"):
            assert (tmp_path / "ray" / run / name).read_text() == (tmp_path / "local" / run / name).read_text()
        assert (tmp_path / "ray" / run / "checkpoints" / "fast.pt").exists()


WORKER_SCRIPT = """
import multiprocessing, os, time
from concurrent.futures import ProcessPoolExecutor
from layered.sweep import _init_worker
if __name__ == "__main__":
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_init_worker, initargs=(os.getpid(), None, 1))
    print(pool.submit(os.getpid).result(), flush=True)
    pool.submit(time.sleep, 120)
    time.sleep(120)
"""


def test_a_sweep_runs_a_process_per_run_or_per_setup_and_no_more_than_it_is_given(tmp_path):
    jobs = plan([PENDULUM / "td3.toml", PENDULUM / "tla-c.toml"], 3, tmp_path)
    assert [[job.out.name for job in task] for task in tasks(jobs, vectorize=True)] == [["seed0", "seed1", "seed2"]] * 2
    assert len(tasks(jobs, vectorize=False)) == 6
    assert [process_count(jobs, j) for j in (1, 4, 8)] == [1, 4, 6]
    assert [process_count(jobs, j, vectorize=True) for j in (1, 4)] == [1, 2]


def test_a_setups_seeds_cut_into_groups_train_as_a_group_each():
    out = Path("/sweep")
    jobs = plan([PENDULUM / "td3.toml", PENDULUM / "tla-c.toml"], 5, out, group_size=2)
    groups = [[job.out.relative_to(out).as_posix() for job in task] for task in tasks(jobs, vectorize=True)]
    assert groups == [[f"pendulum/{r}/seeds{a}-{b}/seed{k}" for k in range(a, b + 1)]
                      for a, b in ((0, 1), (2, 3), (4, 4)) for r in ("td3", "tla-c")]
    assert [process_count(jobs, j, vectorize=True) for j in (2, 8)] == [2, 6]
    assert {job.label for job in jobs} == {"pendulum/td3", "pendulum/tla-c"}  # reported as two setups


def test_a_sweeps_worker_sizes_its_environments_workers_to_its_share_of_the_cores():
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=context, initializer=_init_worker, initargs=(os.getpid(), None, 1)) as pool:
        assert pool.submit(usable_cores).result() == 1
        assert pool.submit(worker_count, "auto", 8, None).result() == 0


def _threads(out: Path, vectorize: bool) -> int:
    """The torch threads a local sweep's worker gives a run, or the group of a setup (training stood in for)."""
    import torch

    import layered.group
    import layered.runs

    seen = []
    row = {"return_mean": 0.0, "repetition": 0.0}
    layered.group.train_group = lambda *a, **k: seen.append(torch.get_num_threads()) or [[row]]
    layered.runs.train = lambda *a, **k: seen.append(torch.get_num_threads()) or [row]
    jobs = plan([PENDULUM / "td3.toml"], 1, out)
    run_group(jobs) if vectorize else _one(jobs)
    return seen[0]


@pytest.mark.skipif(usable_cores() < 2, reason="needs two cores")
@pytest.mark.parametrize("vectorize", [False, True], ids=["run", "group"])
@pytest.mark.parametrize(("share", "given", "threads"), [(1, None, 1), (2, None, 2), (2, 1, 1), (1, 3, 3)])
def test_a_local_sweeps_runs_and_groups_compute_on_their_share_of_the_cores(share, given, threads, vectorize,
                                                                             tmp_path):
    """Not torch's default of every core, which a worker's torch had taken before it was given its share (two
    groups of two torch threads each on two cores ran 2.3 times slower than with one each), nor one thread
    where a run has more cores to itself; and the threads given (`sweep --threads`) where they are."""
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=context, initializer=_init_worker,
                             initargs=(os.getpid(), None, share, given)) as pool:
        assert pool.submit(_threads, tmp_path, vectorize).result() == threads


def _alive(pid: int) -> bool:
    status = Path(f"/proc/{pid}/status")
    return status.exists() and "\tZ" not in status.read_text().split("State:")[1].splitlines()[0]


@pytest.mark.skipif(not Path("/proc").exists(), reason="reads process states from /proc")
def test_sweep_workers_end_when_the_sweep_process_is_killed(tmp_path):
    script = tmp_path / "sweep_parent.py"
    script.write_text(WORKER_SCRIPT)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    assert _alive(worker)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 15
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _alive(worker)


def _started_sweep(out, jobs=2, *vectorize):
    """A sweep of 4 runs (or 2 groups, with `--vectorize`) on 2 workers, once both workers are training (each has
    a checkpoint)."""
    command = [sys.executable, "-m", "layered.cli", "sweep", PENDULUM / "td3.toml", PENDULUM / "tla-o.toml", *TINY,
               "eval.fresh_episodes=0", "--seeds", 2, "--jobs", jobs, "--steps", 3000, "--out", out, *vectorize]
    proc = subprocess.Popen(list(map(str, command)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    checkpoint = "group.pt" if vectorize else "run.pt"
    while len(list(out.rglob(checkpoint))) < jobs and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert len(list(out.rglob(checkpoint))) >= jobs, "the workers never checkpointed"
    return proc


@pytest.mark.parametrize("signals", [1, 2])
def test_a_signal_to_the_sweep_alone_starts_no_new_run_and_stops_the_running_ones(tmp_path, signals):
    out = tmp_path / "sw"
    proc = _started_sweep(out)
    for _ in range(signals):
        proc.send_signal(signal.SIGINT)  # the sweep process only: its workers are in sessions of their own
        time.sleep(0.3)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("layered:")]
    how = "at their next episode end" if signals == 1 else "at once, from their last checkpoints"
    assert len(lines) == 2 and "no new run starts" in lines[0] and how in lines[1], stderr
    assert stderr.count("no new run starts") == 1 and stdout.count("not started") == 2
    assert not list(out.rglob("results.json")) and len(list(out.glob("*/*/seed*"))) == 2
    again = layered_here("sweep", PENDULUM / "td3.toml", PENDULUM / "tla-o.toml", *TINY, "eval.fresh_episodes=0",
                         "--seeds", 2, "--jobs", 2, "--steps", 300, "--out", out)
    assert again.returncode == 2 and "--steps 3000, not --steps 300" in again.stderr  # resumed only as it was made


def test_a_signal_to_a_vectorized_sweep_stops_its_groups_at_their_next_step(tmp_path):
    proc = _started_sweep(tmp_path / "sw", 2, "--vectorize")
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    lines = [line for line in stderr.splitlines() if line.startswith("layered:")]
    assert proc.returncode == 130 and len(lines) == 2, stderr
    assert "the running ones stop at their next step" in lines[0] and "stopped at their next step" in lines[1]
    assert len(list((tmp_path / "sw").rglob("group.pt"))) == 2 and not list((tmp_path / "sw").rglob("results.json"))


def test_comma_separated_values_make_a_grid_of_setups_each_reported_on_its_own(tmp_path):
    from layered.overrides import grid, split_values
    from layered.sweep import plan

    assert split_values('[32, 32],"a,b",{x = 1, y = 2},3') == ["[32, 32]", '"a,b"', "{x = 1, y = 2}", "3"]
    assert [named for _, named in grid(["a=1,2", "b=[1, 2]", "c=x,y"])] == [
        ["a=1", "c=x"], ["a=1", "c=y"], ["a=2", "c=x"], ["a=2", "c=y"]]
    # the same setups written otherwise (another key order, numbers written otherwise) get the same names
    def names(overrides):
        return sorted(",".join(named) for _, named in grid(overrides))

    assert names(["c=x", "b=0.50,1e-3", "a=1,2"]) == names(["a=1,2", "b=5e-1,0.001"]) == [
        "a=1,b=0.001", "a=1,b=0.5", "a=2,b=0.001", "a=2,b=0.5"]
    legacy = tmp_path / "legacy" / "pendulum" / "tla-c" / "learner.lr=1e-3"  # (named as written, by a sweep before)
    legacy.mkdir(parents=True)
    folders = {str(job.out.parent.relative_to(tmp_path / "legacy")) for job in plan(
        [PENDULUM / "tla-c.toml"], 1, tmp_path / "legacy", [*TINY, "learner.lr=1e-3,3e-4"], 300)}
    assert folders == {"pendulum/tla-c/learner.lr=1e-3", "pendulum/tla-c/learner.lr=0.0003"}
    out = tmp_path / "grid"
    jobs = plan([PENDULUM / "tla-c.toml"], 2, out, [*TINY, "layers.fast.action_penalty=0.5,2"], 300)
    assert sorted(str(job.out.relative_to(out)) for job in jobs) == [
        f"pendulum/tla-c/layers.fast.action_penalty={v}/seed{k}" for v in ("0.5", "2") for k in (0, 1)]
    assert {job.recipe["layers"][1]["action_penalty"] for job in jobs} == {0.5, 2.0}
    proc = sweep(PENDULUM / "tla-c.toml", *TINY, "layers.fast.action_penalty=0.5,2", "--seeds", 1, "--jobs", 2,
                 "--steps", 150, "--out", out)
    assert proc.returncode == 0, proc.stderr
    report = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(out), "--out", str(tmp_path / "r")],
                            capture_output=True, text=True)
    assert report.returncode == 0, report.stderr
    summary = (tmp_path / "r" / "summary.csv").read_text().splitlines()
    assert len(summary) == 3 and {line.split(",")[1] for line in summary[1:]} == {
        "pendulum/tla-c layers.fast.action_penalty=0.5", "pendulum/tla-c layers.fast.action_penalty=2"}


def test_a_vectorised_sweep_trains_each_setups_seeds_as_one_group(tmp_path):
    out = tmp_path / "vec"
    args = (PENDULUM / "td3.toml", *TINY, "layers.fast.action_penalty=0,1", "--seeds", 2, "--jobs", 2, "--steps", 150,
            "--vectorize", "--out", out)
    proc = sweep(*args)
    assert proc.returncode == 0, proc.stderr
    runs = sorted(p.parent.relative_to(out).as_posix() for p in out.rglob("results.json"))
    assert runs == [f"pendulum/td3/layers.fast.action_penalty={v}/seed{k}" for v in (0, 1) for k in (0, 1)]
    assert '"group": [\n    0,\n    1\n  ]' in (out / runs[0] / "run.json").read_text()
    assert layered_here("sweep", *args).stdout.count("skipped") == 4
    plain = layered_here("sweep", *[a for a in args if a != "--vectorize"]).stdout  # the same seeds, as single runs
    assert plain.count("already finished; trained as a seed of a group") == 4, plain
    cut = sweep(PENDULUM / "td3.toml", *TINY, "--seeds", 3, "--jobs", 2, "--steps", 150, "--vectorize",
                "--group-size", 2, "--out", tmp_path / "cut")
    assert cut.returncode == 0, cut.stderr
    runs = sorted(p.parent.relative_to(tmp_path / "cut").as_posix() for p in (tmp_path / "cut").rglob("results.json"))
    assert runs == ["pendulum/td3/seeds0-1/seed0", "pendulum/td3/seeds0-1/seed1", "pendulum/td3/seeds2-2/seed2"]
    assert '"group": [\n    2\n  ]' in (tmp_path / "cut" / runs[2] / "run.json").read_text()
    alone = layered_here("sweep", PENDULUM / "td3.toml", "--group-size", 2, "--out", tmp_path / "u")
    assert alone.returncode == 2 and "needs --vectorize" in alone.stderr and not (tmp_path / "u").exists()
    on_ray = layered_here("sweep", PENDULUM / "td3.toml", "--threads", 1, "--backend", "ray", "--out", tmp_path / "r")
    assert on_ray.returncode == 2 and "a Ray task computes on one thread" in on_ray.stderr
    assert not (tmp_path / "r").exists()
    examples = PENDULUM.parent.parent / "docs" / "examples"  # a plugin's learner, which no group stacks
    refused = layered_here("sweep", examples / "pendulum-centre.toml", "--plugin", examples / "centre.py",
                           "--vectorize", "--out", tmp_path / "t")
    assert refused.returncode == 2 and "'centre' learner" in refused.stderr and not (tmp_path / "t").exists()


def test_a_sweep_whose_worker_is_killed_says_so_in_a_line_per_run_and_the_same_command_continues(tmp_path):
    """A worker killed (kill -9, the out-of-memory killer) broke the pool: the sweep ended in a traceback, saying
    nothing of the runs it had."""
    killer = tmp_path / "killer.py"
    killer.write_text("import multiprocessing, os, signal\n\n"
                      "if multiprocessing.parent_process() is not None and not os.path.exists(os.environ['SPARED']):\n"
                      "    os.kill(os.getpid(), signal.SIGKILL)  # (a sweep's worker, as it loads the run's plugins)\n")
    out, spared = tmp_path / "sw", tmp_path / "spared"
    args = (PENDULUM / "td3.toml", *TINY, "--seeds", 1, "--jobs", 1, "--steps", 100, "--out", out, "--plugin", killer)
    os.environ["SPARED"] = str(spared)
    try:
        proc = sweep(*args)
        assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert "failed  " in proc.stdout and "a worker process of the sweep ended unexpectedly" in proc.stdout
        spared.touch()
        again = sweep(*args)
    finally:
        del os.environ["SPARED"]
    assert again.returncode == 0 and "1 of 1 runs finished" in again.stdout, again.stderr


def test_a_run_whose_settings_resume_changed_is_the_sweeps_with_those_changes(tmp_path):
    """After `layered resume RUN --set` on one of a sweep's runs (recorded in its run.json), the same sweep takes
    the run as its own, with its changed settings; a recipe changed otherwise is still refused."""
    from layered.recipe import RecipeError, load_recipe, resolved
    from layered.rundir import record_change

    out = tmp_path / "sw"
    jobs = plan([PENDULUM / "td3.toml"], 1, out, TINY, 100)
    run = jobs[0].out
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"label": "x", "max_steps": 100, "plugins": [], "group": []}))
    changed = resolved(load_recipe(jobs[0].recipe, ["layers.fast.learner.lr=1e-4"]))
    record_change(run, tomli_w.dumps(changed), {"phase": 0, "step": 50, "set": ["layers.fast.learner.lr=1e-4"]})
    [job] = plan([PENDULUM / "td3.toml"], 1, out, TINY, 100)
    assert job.recipe["layers"][0]["learner"]["lr"] == 1e-4 and job.recipe == tomllib.loads(tomli_w.dumps(changed))
    (run / "recipe.toml").write_text(tomli_w.dumps(resolved(load_recipe(jobs[0].recipe, ["learner.lr=1e-3"]))))
    with pytest.raises(RecipeError, match="holds a different recipe"):
        plan([PENDULUM / "td3.toml"], 1, out, TINY, 100)
