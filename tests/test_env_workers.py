"""A group's environments stepped in worker processes, or in threads, are the environments stepped here
one after another: the same observations, rewards and flags row by row, the same snapshots; a worker's or
a thread's failure is the group's error."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import pytest

from layered import cores
from layered.env_group import EnvGroup
from layered.group_eval import torch_aside
from layered.env_workers import SPIN_SECONDS, EnvWorkerError, EnvWorkers, open_envs, spins, thread_count, worker_count

ENV = "Hopper-v5"  # episodes of different lengths, and a MuJoCo state in every snapshot


@pytest.mark.parametrize("setting, rows, cores, expected", [
    ("auto", 8, 2, 0),  # two cores: the learners' (the rows step in the training process)
    ("auto", 8, 4, 2),  # half the cores
    ("auto", 32, 16, 8),
    ("auto", 4, 16, 4),  # never more workers than rows
    ("auto", 1, 16, 0),  # one row: nothing to share out
    (3, 2, 2, 2),  # a number is taken as given, at most one per row
    (0, 8, 16, 0),
])
def test_how_many_workers_step_the_rows(setting, rows, cores, expected):
    assert worker_count(setting, rows, cores) == expected


@pytest.mark.parametrize("setting, rows, workers, evaluation, parallel, cores, expected", [
    ("auto", 8, 0, False, True, 2, 1),  # training, in the training process: one thread, beside the update
    ("auto", 1, 0, False, True, 2, 0),  # a single row steps in the process's own thread
    ("auto", 8, 0, False, True, 1, 0),  # so do the rows of a process with one core (a sweep's group)
    ("auto", 32, 8, False, True, 16, 0),  # a worker steps beside the update already
    ("auto", 80, 0, True, True, 2, 2),  # an evaluation: every core
    ("auto", 80, 0, True, False, 2, 1),  # ... unless the rows would only take turns
    ("auto", 320, 8, True, True, 16, 2),  # the cores shared out among the workers
    ("auto", 320, 8, True, True, 8, 0),  # a core each: none
    ("auto", 16, 8, True, True, 32, 2),  # never more threads than a worker's rows
    (3, 8, 0, False, True, 2, 3),  # a number is taken as given
    (2, 32, 8, True, False, 16, 2),
    (0, 8, 0, True, True, 2, 0),
])
def test_how_many_threads_step_a_process_rows(setting, rows, workers, evaluation, parallel, cores, expected):
    assert thread_count(setting, rows, workers, evaluation, parallel, cores) == expected


@pytest.mark.parametrize("setting, workers, threads, gpu, cores, expected", [
    ("auto", 8, 0, True, 16, True),  # learners on a GPU, a core for each worker and the training process, and more
    ("auto", 8, 0, False, 16, False),  # learners on the CPU: its cores are theirs
    ("auto", 2, 0, True, 3, False),  # no core to spare
    ("auto", 2, 0, True, 4, True),
    ("auto", 8, 2, True, 16, False),  # two threads stepping in each worker: every core busy
    ("auto", 0, 0, True, 16, False),  # no workers: nothing to wait for
    ("spin", 8, 0, False, 2, True),  # a setting is taken as given
    ("spin", 0, 0, True, 16, False),
    ("sleep", 8, 0, True, 16, False),
])
def test_when_the_training_process_and_its_workers_spin(setting, workers, threads, gpu, cores, expected):
    assert spins(setting, workers, threads, gpu, cores) == expected


def test_open_envs_spins_as_the_setting_and_the_learners_device_say():
    envs = [open_envs("Pendulum-v1", 2, 1, wait="spin"), open_envs("Pendulum-v1", 2, 1, wait="auto"),
            open_envs("Pendulum-v1", 2, 0, wait="spin")]
    try:
        assert isinstance(envs[0], EnvWorkers) and envs[0].spin
        assert isinstance(envs[1], EnvWorkers) and not envs[1].spin  # the learners on the CPU
        assert isinstance(envs[2], EnvGroup)  # no workers
    finally:
        for each in envs:
            each.close()


def test_a_process_given_a_share_of_the_cores_counts_those_alone(monkeypatch):
    monkeypatch.setattr(cores, "_SHARE", None)
    machine = cores.usable_cores()
    cores.share_cores(0)  # more processes than cores: each still has one
    assert cores.usable_cores() == 1
    cores.share_cores(machine + 5)  # never more than the process may run on
    assert cores.usable_cores() == machine


def test_open_envs_steps_here_without_workers_and_in_processes_with_them():
    here = open_envs("Pendulum-v1", 3, 0)
    there = open_envs("Pendulum-v1", 3, 2)
    try:
        assert isinstance(here, EnvGroup) and isinstance(there, EnvWorkers)
        assert there.observation_space == here.observation_space and there.action_space == here.action_space
    finally:
        here.close()
        there.close()


def play(envs, steps: int, seed: int, snapshot_at: int | None = None, restart: bool = False):
    """Random actions in random subsets of the rows, ended rows reset (by the step itself, with `restart`); what
    every step gave, and the snapshots and observations at `snapshot_at`."""
    rng = np.random.default_rng(seed)
    rows = len(envs.obs)
    envs.reset(np.ones(rows, bool), [10 + k for k in range(rows)])
    trace, saved = [envs.obs.copy()], None
    for t in range(steps):
        if t == snapshot_at:
            saved = (envs.snapshots(), envs.obs.copy())
        actions = rng.uniform(-1, 1, (rows, 3)).astype(np.float32)
        mask = rng.random(rows) < 0.7
        envs.step_async(actions, mask, restart)
        reward, terminated, truncated = envs.step_wait()
        assert not reward[~mask].any() and not terminated[~mask].any() and not truncated[~mask].any()
        trace += [reward.copy(), terminated.copy(), truncated.copy(), (envs.last if restart else envs.obs).copy()]
        if not restart:
            envs.reset(terminated | truncated, [None] * rows)
        trace.append(envs.obs.copy())
    return trace, saved


def assert_same_trace(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and np.array_equal(x, y)


def test_rows_stepped_in_workers_give_what_they_give_here_and_their_snapshots_continue_them():
    here, there = EnvGroup(ENV, 5), EnvWorkers(ENV, 5, 2)
    try:
        expected, saved_here = play(here, 120, seed=1, snapshot_at=60)
        got, saved_there = play(there, 120, seed=1, snapshot_at=60)
        if sys.platform == "linux":  # (snapshots are arrays: a worker that imported torch for them held 130 MiB more)
            assert not any("libtorch" in Path(f"/proc/{p.pid}/maps").read_text() for p in there._processes)
        assert_same_trace(expected, got)
        assert any(t.any() for t in expected[2::5]), "some episodes ended (Hopper falls under random actions)"
        assert np.array_equal(saved_here[1], saved_there[1])
    finally:
        there.close()
    later = EnvWorkers(ENV, 5, 3)  # other slices: a snapshot belongs to its row, not to its worker
    try:
        later.restore(*saved_there)
        here.restore(*saved_here)
        rng = np.random.default_rng(2)
        for _ in range(30):
            actions, mask = rng.uniform(-1, 1, (5, 3)).astype(np.float32), rng.random(5) < 0.8
            assert_same_trace(here.step(actions, mask), later.step(actions, mask))
            assert np.array_equal(here.obs, later.obs)
    finally:
        later.close()
        here.close()


@pytest.mark.parametrize("threads", [1, 2, 3, 8])  # 8: more threads than rows
def test_rows_stepped_in_threads_give_what_they_give_one_after_another(threads):
    alone, threaded = EnvGroup(ENV, 5), EnvGroup(ENV, 5, threads)
    try:
        expected, saved = play(alone, 120, seed=1, snapshot_at=60)
        got, saved_threaded = play(threaded, 120, seed=1, snapshot_at=60)
        assert_same_trace(expected, got)
        assert np.array_equal(saved[1], saved_threaded[1])
    finally:
        alone.close()
        threaded.close()


def test_rows_stepped_in_threads_of_workers_give_what_they_give_here():
    here, there = EnvGroup(ENV, 5), EnvWorkers(ENV, 5, 2, threads=2)
    try:
        assert_same_trace(play(here, 80, seed=3)[0], play(there, 80, seed=3)[0])
    finally:
        here.close()
        there.close()


@pytest.mark.parametrize("make", [lambda: EnvGroup(ENV, 5), lambda: EnvGroup(ENV, 5, 2), lambda: EnvWorkers(ENV, 5, 2),
                                  lambda: EnvWorkers(ENV, 5, 2, threads=2), lambda: EnvWorkers(ENV, 5, 2, spin=True)],
                         ids=["here", "threads", "workers", "threads-of-workers", "spinning-workers"])
def test_a_step_that_restarts_ended_episodes_gives_what_a_step_and_a_reset_give(make):
    alone, restarting = EnvGroup(ENV, 5), make()
    try:
        expected, saved = play(alone, 120, seed=4, snapshot_at=70)
        got, saved_restarting = play(restarting, 120, seed=4, snapshot_at=70, restart=True)
        assert sum(t.sum() for t in expected[2::5]) >= 5, "episodes ended (Hopper falls under random actions)"
        assert_same_trace(expected, got)  # the step's observations in `last`, the next episodes' first in `obs`
        assert np.array_equal(saved[1], saved_restarting[1])
    finally:
        alone.close()
        restarting.close()


def test_a_failure_in_a_thread_is_raised_when_the_step_is_collected_and_the_rows_step_again_after():
    envs = EnvGroup("Pendulum-v1", 4, threads=2)
    try:
        envs.reset(np.ones(4, bool), [0, 1, 2, 3])
        broken, step = envs.envs[3], envs.envs[3].step
        broken.step = lambda action: (_ for _ in ()).throw(ValueError("row 3 broke"))
        envs.step_async(np.zeros((4, 1), np.float32), np.ones(4, bool))  # raises nothing yet
        with pytest.raises(ValueError, match="row 3 broke"):
            envs.step_wait()
        broken.step = step
        reward, _, _ = envs.step(np.zeros((4, 1), np.float32), np.ones(4, bool))
        assert (reward < 0).all()
    finally:
        envs.close()


@pytest.mark.parametrize("make", [lambda: EnvWorkers("Pendulum-v1", 4, 2), lambda: EnvGroup("Pendulum-v1", 4, 2)],
                         ids=["workers", "threads"])
def test_a_step_can_be_collected_after_other_work(make):
    envs = make()
    try:
        envs.reset(np.ones(4, bool), [0, 1, 2, 3])
        before = envs.obs.copy()
        actions, mask = np.zeros((4, 1), np.float32), np.array([True, False, True, False])
        envs.step_async(actions, mask)
        actions[:], mask[:] = 2.0, True  # the caller's arrays are its own again once the step is asked for
        reward, _, _ = envs.step_wait()
        assert np.array_equal(envs.obs[[1, 3]], before[[1, 3]]) and not np.array_equal(envs.obs[0], before[0])
        assert reward[0] < 0 and reward[1] == 0
    finally:
        envs.close()


@pytest.mark.parametrize("spin", [False, True], ids=["sleeping", "spinning"])
def test_a_failure_in_a_worker_is_raised_with_its_traceback_and_a_dead_worker_is_named(spin):
    envs = EnvWorkers(ENV, 3, 2, spin=spin)
    processes = list(envs._processes)
    try:
        with pytest.raises(EnvWorkerError, match="Traceback"):
            envs.restore([{}, {}, {}], envs.obs.copy())  # no state in these snapshots
        envs._processes[1].kill()
        envs._processes[1].join()
        with pytest.raises(EnvWorkerError, match="stepping row 2 ended unexpectedly"):
            envs.step(np.zeros((3, 3), np.float32), np.ones(3, bool))
    finally:
        envs.close()
    assert not any(process.is_alive() for process in processes)


def test_spinning_workers_sleep_when_nothing_comes_and_answer_when_woken():
    envs = EnvWorkers("Pendulum-v1", 2, 2, spin=True)
    processes = list(envs._processes)
    try:
        envs.reset(np.ones(2, bool), [0, 1])
        assert SPIN_SECONDS < 0.3
        time.sleep(0.3)  # longer than they spin
        used = [cpu_seconds(process.pid) for process in processes]
        time.sleep(0.3)
        assert all(cpu_seconds(process.pid) - u < 0.1 for process, u in zip(processes, used, strict=True))  # asleep
        reward, _, _ = envs.step(np.zeros((2, 1), np.float32), np.ones(2, bool))
        assert (reward < 0).all()
    finally:
        envs.close()
    assert not any(process.is_alive() for process in processes)


def cpu_seconds(pid: int) -> float:
    """The CPU time a process has used, from /proc (user and system)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.parametrize("spin", [False, True], ids=["sleeping", "spinning"])
def test_workers_end_when_the_process_that_started_them_is_killed(spin):
    starter = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from layered.env_workers import EnvWorkers\n"
        f"envs = EnvWorkers('Pendulum-v1', 2, 2, spin={spin})\n"
        "print(*[process.pid for process in envs._processes], flush=True)\n"
        "time.sleep(60)\n")], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(pid) for pid in starter.stdout.readline().split()]
        assert len(pids) == 2 and all(alive(pid) for pid in pids)
        starter.kill()
        starter.wait()
        until = time.monotonic() + 10
        while any(alive(pid) for pid in pids) and time.monotonic() < until:
            time.sleep(0.05)
        assert not any(alive(pid) for pid in pids)
    finally:
        starter.kill()


def alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_workers_ignore_a_ctrl_c_at_the_terminal_and_are_gone_after_close():
    envs = EnvWorkers("Pendulum-v1", 2, 2)
    processes = list(envs._processes)
    try:
        envs.reset(np.ones(2, bool), [0, 1])
        for process in processes:
            os.kill(process.pid, signal.SIGINT)  # what a Ctrl-C sends every process of the terminal's group
        envs.step(np.zeros((2, 1), np.float32), np.ones(2, bool))
        assert all(process.is_alive() for process in processes)
    finally:
        envs.close()
    assert not any(process.is_alive() for process in processes)


@pytest.mark.parametrize("make, during", [
    (lambda: EnvGroup("Pendulum-v1", 2, 2), 1),  # two threads here
    (lambda: EnvWorkers("Pendulum-v1", 2, 2), 1),  # two workers
    (lambda: EnvWorkers("Pendulum-v1", 2, 1, threads=2), 1),  # a worker's two threads
    (lambda: EnvGroup("Pendulum-v1", 2, 1), 3),  # one thread: torch's cores are free
    (lambda: EnvGroup("Pendulum-v1", 2, 0), 3),
], ids=["threads", "workers", "threads-in-a-worker", "one-thread", "the-caller"])
def test_an_evaluation_stepping_rows_in_several_threads_computes_on_one_torch_thread(make, during):
    before = torch.get_num_threads()
    envs = make()
    try:
        torch.set_num_threads(3)
        with torch_aside(envs):
            assert torch.get_num_threads() == during  # its idle workers would spin on the rows' cores
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
        envs.close()


def test_an_evaluations_threads_step_its_environments_on_that_many_cores_and_no_longer_after(monkeypatch):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda _: set(range(8)))
    assert thread_count("auto", 10, 0, evaluation=True) == 8
    with cores.cores_given(1):  # `layered eval --threads 1`
        assert cores.usable_cores() == 1 and thread_count("auto", 10, 0, evaluation=True) == 0
    with cores.cores_given(None):  # no --threads: as before
        assert thread_count("auto", 10, 0, evaluation=True) == 8
    assert cores.usable_cores() == 8
