"""A group's K environments stepped in worker processes, several rows per worker, through shared memory.

Each worker owns a contiguous slice of the rows, made and stepped by the same functions as in this
process (`layered.env_group`), so a group's numbers do not depend on where its rows step. Actions, row
masks, observations, rewards and flags pass through arrays in shared memory; a pipe per worker carries
one short command per step, and snapshots at checkpoints. The workers step while the caller does other
work between `step_async` and `step_wait` (a group queues its update there). Each side waits for the other
asleep in its pipe, or, where cores are to spare, spinning on it (`spins`): a sleeping process's wake-up
is most of a step's hand-over.

Workers ignore SIGINT (a Ctrl-C at the terminal reaches the whole process group; the training process
decides what it means) and end when their pipe closes, so none outlives the process that started it.
"""

from __future__ import annotations

import ctypes
import itertools
import multiprocessing
import os
import pickle
import select
import signal
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any, Literal

import numpy as np

from layered.cores import usable_cores
from layered.env_group import EnvGroup, Envs, RowThreads, StepResult, reset_rows, spaces
from layered.envs import env_spaces, make_env, restore_env, snapshot_env

WorkersSetting = int | Literal["auto"]
WaitSetting = Literal["auto", "sleep", "spin"]
SPIN_SECONDS = 0.01
"""How long a spinning side polls its pipe before it sleeps in it: longer than a group's training step on a GPU,
shorter than an evaluation or a checkpoint, during which the training's workers sleep."""


class EnvWorkerError(RuntimeError):
    """An environment failed in a worker process (its traceback is in the message), or a worker died."""


def worker_count(setting: WorkersSetting, rows: int, cores: int | None = None) -> int:
    """How many worker processes step `rows` environments: `setting` itself (at most one per row), or for
    `auto` half the usable cores where there are 4 or more (the rest stay with the learners), and none,
    the rows stepping in this process, on smaller machines or for a single row."""
    if setting != "auto":
        return min(setting, rows)
    cores = usable_cores() if cores is None else cores
    return 0 if cores < 4 or rows < 2 else min(rows, cores // 2)


def thread_count(setting: WorkersSetting, rows: int, workers: int, evaluation: bool = False, parallel: bool = True,
                 cores: int | None = None) -> int:
    """How many threads step the rows in each process that steps them (`rows` rows in `workers` worker
    processes, or in this one where `workers` is 0): `setting` itself, or for `auto` none for a single row or
    on a single core (a thread's hand-over would cost more than it hides; a sweep's group may have one core).
    While training: one in the training process, so that the rows step beside the update it queues, and none
    in a worker, which steps beside it already. For an evaluation, which has nothing else to run, where the
    rows step in `parallel` (`EnvFamily.steps_in_parallel`; other rows would only take turns): the cores
    shared out among the processes that step them."""
    if setting != "auto":
        return setting
    cores = usable_cores() if cores is None else cores
    if rows < 2 or cores < 2:
        return 0
    if evaluation and parallel:
        each = min(-(-rows // max(workers, 1)), cores // max(workers, 1))
        return each if each >= 2 else 0
    return 0 if workers else 1


def spins(setting: WaitSetting, workers: int, threads: int, gpu: bool, cores: int | None = None) -> bool:
    """Whether the training process and its `workers` (each stepping its rows in `threads` threads) wait for each
    other spinning rather than asleep: `setting` itself, or for `auto` where the learners are on a GPU (the
    training process's cores are free while they compute) and every process that spins or steps has a core of
    its own with one to spare. On a CPU the learners need the cores a spinning side would take."""
    if not workers or setting == "sleep":
        return False
    if setting == "spin":
        return True
    cores = usable_cores() if cores is None else cores
    return gpu and workers * max(threads, 1) + 1 < cores


def open_envs(env_id: str, rows: int, workers: WorkersSetting, threads: WorkersSetting = 0,
              evaluation: bool = False, wait: WaitSetting = "sleep", gpu: bool = False) -> Envs:
    """`rows` environments of `env_id` (for training, or for an `evaluation`), in `worker_count(workers, rows)`
    worker processes (none: in this one), each stepping its rows in `thread_count(threads, ...)` threads, the
    processes waiting for each other as `spins(wait, ..., gpu)` says (`gpu`: the learners are on one)."""
    count = worker_count(workers, rows)
    each = thread_count(threads, rows, count, evaluation, env_spaces(env_id).parallel)
    if not count:
        return EnvGroup(env_id, rows, each)
    return EnvWorkers(env_id, rows, count, each, spins(wait, count, each, gpu))


def _context() -> Any:
    """Where workers come from: forked from a clean server process that has imported the environments
    (fast, and nothing of this process's torch state is forked), or fresh interpreters where there is none."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


class _Shared:
    """The arrays one step passes between the group and its workers, in shared memory."""

    def __init__(self, rows: int, obs_dim: int, action_dim: int, context: Any) -> None:
        self.shape = (rows, obs_dim, action_dim)
        self.raw = {"obs": context.RawArray(ctypes.c_float, rows * obs_dim),
                    "last": context.RawArray(ctypes.c_float, rows * obs_dim),
                    "actions": context.RawArray(ctypes.c_float, rows * action_dim),
                    "rows": context.RawArray(ctypes.c_bool, rows),
                    "reward": context.RawArray(ctypes.c_double, rows),
                    "terminated": context.RawArray(ctypes.c_bool, rows),
                    "truncated": context.RawArray(ctypes.c_bool, rows)}
        self.views()

    def views(self) -> None:
        """The arrays as numpy views (again in a worker, which receives the raw arrays pickled)."""
        rows, obs_dim, action_dim = self.shape
        raw = self.raw
        self.obs = np.frombuffer(raw["obs"], np.float32).reshape(rows, obs_dim)
        self.last = np.frombuffer(raw["last"], np.float32).reshape(rows, obs_dim)
        self.actions = np.frombuffer(raw["actions"], np.float32).reshape(rows, action_dim)
        self.rows = np.frombuffer(raw["rows"], bool)
        self.result: StepResult = (np.frombuffer(raw["reward"], np.float64), np.frombuffer(raw["terminated"], bool),
                                   np.frombuffer(raw["truncated"], bool))

    def __getstate__(self) -> dict[str, Any]:
        return {"shape": self.shape, "raw": self.raw}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.shape, self.raw = state["shape"], state["raw"]
        self.views()


class EnvWorkers(Envs):
    """K environments stepped in `workers` processes, rows split into contiguous slices (`Envs`); with `spin`, the
    workers and this process poll their pipes for `SPIN_SECONDS` before they sleep in them."""

    def __init__(self, env_id: str, rows: int, workers: int, threads: int = 0, spin: bool = False) -> None:
        self.env_id = env_id
        self.spin = spin
        self.observation_space, self.action_space = spaces(env_spaces(env_id))  # (read once per process)
        context = _context()
        self._shared = _Shared(rows, self.observation_space.shape[0], self.action_space.shape[0], context)
        self.obs, self.last = self._shared.obs, self._shared.last
        bounds = np.linspace(0, rows, workers + 1).round().astype(int).tolist()
        self._slices = [slice(a, b) for a, b in itertools.pairwise(bounds)]
        self._pipes: list[Connection] = []
        self._answers: list[select.poll] = []  # (spinning: for each pipe, whether its answer is there)
        self._processes = []
        self._asked: list[int] = []
        self.stepping = workers * max(threads, 1)
        try:
            for part in self._slices:
                mine, theirs = context.Pipe()
                process = context.Process(target=_serve, args=(theirs, env_id, part, threads, self._shared, spin),
                                          daemon=True, name=f"layered-envs-{part.start}-{part.stop - 1}")
                process.start()
                theirs.close()
                self._pipes.append(mine)
                if spin:
                    self._answers.append(_poller(mine))
                self._processes.append(process)
            self._asked = list(range(len(self._slices)))
            self._collect()  # each worker has made its environments
        except BaseException:
            self.close()
            raise

    def reset(self, rows: np.ndarray, seeds: Sequence[int | None]) -> None:
        self._shared.rows[:] = rows
        self._ask("reset", list(seeds), rows)
        self._collect()

    def step_async(self, actions: np.ndarray, rows: np.ndarray, restart: bool = False) -> None:
        assert not self._asked, "a step is under way: collect it with step_wait first"
        self._shared.actions[:] = actions
        self._shared.rows[:] = rows
        for array in self._shared.result:
            array[:] = 0  # the rows not stepped: zero and False
        if restart:
            np.copyto(self.last, self.obs, where=~rows[:, None])  # (the rows not stepped end where they were)
        self._ask("step and restart" if restart else "step", None, rows)

    def step_wait(self) -> StepResult:
        self._collect()
        return tuple(part.copy() for part in self._shared.result)  # type: ignore[return-value]

    def snapshots(self) -> list[dict[str, Any]]:
        self._ask("snapshot", None)
        return [snapshot for part in self._collect() for snapshot in part]

    def restore(self, snapshots: Sequence[dict[str, Any]], obs: np.ndarray) -> None:
        if len(snapshots) != len(self.obs):
            raise ValueError(f"{len(snapshots)} snapshots for {len(self.obs)} environments")
        self._ask("restore", list(snapshots))
        self._collect()
        self.obs[:] = obs

    def close(self) -> None:
        for pipe in self._pipes:
            try:
                pipe.send_bytes(pickle.dumps(("close", None)))
            except OSError:
                pass  # the worker is gone already
        for process in self._processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()
                process.join()
        for pipe in self._pipes:
            pipe.close()
        self._pipes, self._answers, self._processes, self._asked = [], [], [], []

    def _ask(self, command: str, per_row: list[Any] | None, rows: np.ndarray | None = None) -> None:
        """Send `command` to every worker (with `rows`, those holding a row of the mask), with its slice of
        `per_row` (one entry per row) if given."""
        self._asked = [w for w, part in enumerate(self._slices) if rows is None or rows[part].any()]
        for w in self._asked:
            try:
                part = None if per_row is None else per_row[self._slices[w]]
                self._pipes[w].send_bytes(pickle.dumps((command, part)))
            except OSError:
                raise EnvWorkerError(f"{self.env_id}: {self._lost(w)}") from None

    def _collect(self) -> list[Any]:
        """The answers of the workers last asked, in their order; an EnvWorkerError for the first that failed."""
        answers, failure = [], None
        for w in self._asked:
            if self.spin:
                _poll(self._answers[w])
            try:
                ok, answer = pickle.loads(self._pipes[w].recv_bytes())
            except (EOFError, OSError):
                ok, answer = False, self._lost(w)
            if not ok and failure is None:
                failure = answer
            answers.append(answer)
        self._asked = []
        if failure is not None:
            raise EnvWorkerError(f"{self.env_id}: {failure}")
        return answers

    def _lost(self, w: int) -> str:
        first, last = self._slices[w].start, self._slices[w].stop - 1
        rows = f"rows {first}-{last}" if last > first else f"row {first}"
        return f"the worker process stepping {rows} ended unexpectedly"


def _poller(pipe: Connection) -> select.poll:
    """Something that tells at once whether `pipe` has something to read (or has closed)."""
    poller = select.poll()
    poller.register(pipe.fileno(), select.POLLIN)
    return poller


def _poll(poller: select.poll) -> None:
    """Spin until `poller`'s pipe has something to read, for `SPIN_SECONDS` at most (the read that follows sleeps
    until then), handing the core at each turn to any other process waiting for it: a spinner that held its
    core to the end of its time slice made a worker sharing it answer 12 times later."""
    until = time.perf_counter() + SPIN_SECONDS
    while not poller.poll(0) and time.perf_counter() < until:
        os.sched_yield()


def _serve(pipe: Connection, env_id: str, part: slice, threads: int, shared: _Shared, spin: bool = False) -> None:
    """A worker: make the environments of rows `part` and carry out the group's commands on them, its steps
    in `threads` threads, waiting for each spinning on its pipe with `spin`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    envs: list[Any] = []
    stepping: RowThreads | None = None
    try:
        envs = [make_env(env_id) for _ in range(part.start, part.stop)]
        stepping = RowThreads(envs, threads)
        commands = _poller(pipe) if spin else None
        pipe.send_bytes(pickle.dumps((True, None)))
        while True:
            if commands is not None:
                _poll(commands)
            command, argument = pickle.loads(pipe.recv_bytes())
            if command == "close":
                return
            try:
                pipe.send_bytes(pickle.dumps((True, _carry_out(command, argument, envs, stepping, env_id, part,
                                                                shared))))
            except Exception:  # the group raises it, with this traceback
                pipe.send_bytes(pickle.dumps((False, traceback.format_exc())))
    except (EOFError, OSError):
        return  # the group's process is gone
    except Exception:  # making the environments failed
        pipe.send_bytes(pickle.dumps((False, traceback.format_exc())))
    finally:
        if stepping is not None:
            stepping.close()
        for env in envs:
            env.close()


def _carry_out(command: str, argument: Any, envs: list[Any], stepping: RowThreads, env_id: str, part: slice,
               shared: _Shared) -> Any:
    """One command on the worker's rows; what it answers."""
    if command in ("step", "step and restart"):
        stepping.start(shared.actions[part], shared.rows[part], shared.obs[part],
                       tuple(array[part] for array in shared.result),  # type: ignore[arg-type]
                       shared.last[part] if command == "step and restart" else None)
        stepping.wait()
        return None
    if command == "reset":
        reset_rows(envs, shared.rows[part], argument, shared.obs[part])
        return None
    if command == "snapshot":
        return [snapshot_env(env_id, env) for env in envs]
    if command == "restore":
        for env, snapshot in zip(envs, argument, strict=True):
            restore_env(env_id, env, snapshot)
        return None
    raise ValueError(f"unknown command {command!r}")
