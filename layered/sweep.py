"""Experiments over recipes and seeds: every (recipe, seed) pair in its own run directory.

Jobs run in parallel processes, each computing on its share of the cores (one torch thread where there
are as many processes as cores; one on a Ray worker). A finished run (results.json) is
skipped; a stopped one resumes from its last checkpoint, here or, with Ray, on whichever
machine runs it. Ctrl-C stops every run at its next episode end (a group at its next step) with a checkpoint.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import sys
import threading
import time
import tomllib
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import tomli_w
from tqdm import tqdm

from layered.cores import share_cores, usable_cores
from layered.interrupt import SIGNAL_NAMES
from layered.ray_cluster import start_ray
from layered.overrides import setup_names, written_grid
from layered.plugins import load_plugins
from layered.recipe import RecipeError, device_settings, load_recipe, recipe_path, resolved
from layered.rundir import read_run_info, steps_option
from layered.runstate import recipe_differences


@dataclass(frozen=True)
class Job:
    """One training run of a sweep."""

    recipe: dict[str, Any]  # resolved, seed included
    out: Path
    label: str
    max_steps: int | None
    plugins: tuple[str, ...] = ()


@dataclass(frozen=True)
class Outcome:
    """What became of a job."""

    job: Job
    status: str  # "done", "skipped" (already finished), "stopped" (by a signal), "not started" (the sweep stopped),
    # or "failed"
    detail: str


def plan(recipes: Sequence[str | Path], seeds: int, out: Path, overrides: Sequence[str] = (),
         max_steps: int | None = None, plugins: Sequence[str] = (), group_size: int | None = None,
         device: str | None = None) -> list[Job]:
    """The jobs of a sweep; every recipe is validated first, so a bad one stops it before any run; `device` (`--device`)
    on every layer whose learner has a device setting.

    An override `key=a,b,c` gives a setup per value (several such keys: per combination, see
    `overrides.grid`). Run directories are `out/<recipe folder>/<recipe name>[/<key=value,...>]/seed<k>`,
    with as many more of each recipe's parent folders as it takes to tell recipes of the same folder
    and file name apart; a setup's label is the recipe's, then its `key=value`s. With `group_size`, each
    setup's seeds are cut into groups of that many (the last may hold fewer), seed k's run directory in
    its group's folder, `.../seeds<a>-<b>/seed<k>`. Jobs are ordered seed by seed, so a sweep cut short
    still has every setup for its first seeds.
    """
    paths = list(dict.fromkeys(recipe_path(source).resolve() for source in recipes))  # a recipe named twice runs once
    labels = recipe_labels(paths)
    setups = written_grid(overrides)
    on_device = {(path, k): device_settings(path, chosen, device) if device else []
                 for path in paths for k, (chosen, _) in enumerate(setups)}
    jobs = []
    for seed in range(seeds):
        for path in paths:
            for k, (chosen, written) in enumerate(setups):
                named = setup_names(written)
                recipe = load_recipe(path, [*chosen, *on_device[path, k], f"train.seed={seed}"])
                folder = out / labels[path] / ",".join(named).replace("/", "_") if named else out / labels[path]
                as_written = out / labels[path] / ",".join(written).replace("/", "_")
                if named and not folder.exists() and as_written.exists():  # (a setup of a sweep named so before)
                    folder, named = as_written, written
                if group_size is not None:
                    first = seed - seed % group_size
                    folder = folder / f"seeds{first}-{min(first + group_size, seeds) - 1}"
                label = " ".join([labels[path], *named])
                job = Job(resolved(recipe), folder / f"seed{seed}", label, max_steps, tuple(plugins))
                jobs.append(_same_run(job))
    return jobs


def recipe_labels(paths: Sequence[Path]) -> dict[Path, str]:
    """Each recipe's label and run folder: `<folder>/<name>`, lengthened by parent folders where two
    recipes would otherwise share it."""
    depth = {path: 2 for path in paths}
    while True:
        labels = {path: "/".join([*path.parent.parts[-(depth[path] - 1):], path.stem]) for path in paths}
        clashing = [p for p in paths if list(labels.values()).count(labels[p]) > 1 and depth[p] < len(p.parts)]
        if not clashing:
            return labels
        for path in clashing:
            depth[path] += 1


def _same_run(job: Job) -> Job:
    """The job, checked against the run directory an earlier sweep left: it must hold the same recipe and `--steps`,
    or resuming (or skipping it as finished) would mix two experiments. A run whose settings `layered resume --set`
    changed holds the sweep's recipe with those changes: the job goes on with them."""
    existing = job.out / "recipe.toml"
    if existing.exists() and (saved := tomllib.loads(existing.read_text())) != (
            wanted := tomllib.loads(tomli_w.dumps(job.recipe))):
        settings = [s for change in read_run_info(job.out).changes for s in change.get("set", ())] \
            if (job.out / "run.json").exists() else []
        if settings and tomllib.loads(tomli_w.dumps(resolved(load_recipe(job.recipe, settings)))) == saved:
            return _checked_steps(replace(job, recipe=saved))
        differences = recipe_differences(saved, wanted)
        named = "; ".join(differences[:3]) + (f" and {len(differences) - 3} more" if len(differences) > 3 else "")
        raise RecipeError(str(existing), [(None, f"this run directory holds a different recipe ({named}); use "
                                                 "another --out")])
    return _checked_steps(job)


def _checked_steps(job: Job) -> Job:
    """The job, unless its run directory's run was made with another `--steps`."""
    if (job.out / "run.json").exists() and (made := read_run_info(job.out).max_steps) != job.max_steps:
        raise RecipeError(str(job.out / "run.json"), [(None, f"this run was made with {steps_option(made)}, not "
                                                       f"{steps_option(job.max_steps)}; use another --out, or the "
                                                       "same --steps")])
    return job


_STOP: Any = None  # in a worker: the sweep's event, set once it is asked to stop (no new run starts)
_THREADS: int | None = None  # in a worker: the torch threads its runs and groups compute on, None for its share


def _stopped() -> bool:
    """Whether this worker's sweep was asked to stop."""
    return _STOP is not None and _STOP.is_set()


def _finished(job: Job, grouped: bool) -> Outcome:
    """A job whose run is finished: skipped, saying so where it was trained otherwise than this sweep trains it
    (a seed of a group where the sweep trains single runs, or the other way round)."""
    other = bool(read_run_info(job.out).group) != grouped
    how = f"; trained as {'a single run' if grouped else 'a seed of a group'}" if other else ""
    return Outcome(job, "skipped", f"already finished{how}")


def _not_started(job: Job) -> Outcome:
    return Outcome(job, "not started", "the sweep was stopped; the same sweep again starts it")


def run_job(job: Job, threads: int = 1) -> Outcome:
    """Train one job in this process on `threads` torch threads (one on a Ray worker, which shares its
    machine with other tasks), its output going to the run's train.log."""
    import torch

    from layered.interrupt import Stopped
    from layered.runs import train

    if (job.out / "results.json").exists():
        return _finished(job, grouped=False)
    if _stopped():
        return _not_started(job)
    torch.set_num_threads(threads)
    load_plugins(job.plugins)
    job.out.mkdir(parents=True, exist_ok=True)
    with (job.out / "train.log").open("a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            rows = train(load_recipe(job.recipe), job.out, max_steps=job.max_steps, progress=True,
                         label=job.label, resume=True, plugins=job.plugins)
        except Stopped as e:
            print(f"stopped: {e}", file=log)
            return Outcome(job, "stopped", f"phase {e.phase}, step {e.step}; the same sweep again resumes it")
        except KeyboardInterrupt:  # a second signal: at once, from the last checkpoint
            print("stopped at once", file=log)
            return Outcome(job, "stopped", "at once; the same sweep again resumes it from its last checkpoint")
        except Exception as e:  # reported per job; the sweep goes on with the others
            print(f"failed: {e.__class__.__name__}: {e}", file=log)
            return Outcome(job, "failed", f"{e.__class__.__name__}: {e} (see {job.out / 'train.log'})")
    final = rows[-1]
    return Outcome(job, "done", f"return {final['return_mean']:.1f}, repetition {final['repetition']:.1%}")


def run_group(jobs: Sequence[Job]) -> list[Outcome]:
    """Train the seeds of one group (the `jobs`, which differ in their seed alone and share a folder) as one
    group in this process (`layered.group`), on this worker's threads (`_worker_threads`), its output
    going to that folder's group.log. A group stopped by a signal, or killed, continues from its last checkpoint when
    the same sweep runs again."""
    import torch

    from layered.group import train_group
    from layered.group_state import has_group_checkpoint
    from layered.interrupt import Stopped
    from layered.rundir import clear_run_dir

    if all((job.out / "results.json").exists() for job in jobs):
        return [_finished(job, grouped=True) for job in jobs]
    if _stopped():
        return [_not_started(job) for job in jobs]
    torch.set_num_threads(_worker_threads())
    load_plugins(jobs[0].plugins)
    directory = jobs[0].out.parent
    resume = has_group_checkpoint(directory)
    if not resume:
        for job in jobs:
            if job.out.is_dir():
                clear_run_dir(job.out)
    log_path = directory / "group.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            results = train_group([load_recipe(job.recipe) for job in jobs], [job.out for job in jobs], jobs[0].label,
                                  jobs[0].max_steps, progress=True, plugins=jobs[0].plugins, resume=resume)
        except Stopped as e:
            print(f"stopped: {e}", file=log)
            return [Outcome(job, "stopped", f"phase {e.phase}, step {e.step}; the same sweep again resumes its group")
                    for job in jobs]
        except KeyboardInterrupt:  # a second signal: at once, from the last checkpoint
            print("stopped at once", file=log)
            return [Outcome(job, "stopped", "at once; the same sweep again resumes its group from its last checkpoint")
                    for job in jobs]
        except Exception as e:  # reported per job; the sweep goes on with the others
            print(f"failed: {e.__class__.__name__}: {e}", file=log)
            return [Outcome(job, "failed", f"{e.__class__.__name__}: {e} (see {log_path})") for job in jobs]
    return [Outcome(job, "done", f"return {rows[-1]['return_mean']:.1f}, repetition {rows[-1]['repetition']:.1%}")
            for job, rows in zip(jobs, results, strict=True)]


def _one(task: list[Job]) -> list[Outcome]:
    """A local sweep's run, on its worker's threads (`_worker_threads`)."""
    return [run_job(task[0], _worker_threads())]


def _worker_threads() -> int:
    """The torch threads of this worker's runs and groups: those the sweep was given (`--threads`), else the
    worker's share of the cores (one where there are as many workers as cores)."""
    return _THREADS or usable_cores()


@dataclass
class SweepStop:
    """The signals the sweep process received. The first sets the event that keeps workers from
    starting a run and asks each running one (by SIGTERM) to stop where it checkpoints (`where`: a run at its
    next episode end, a group at its next step); a second asks them again, which stops them at once."""

    event: Any
    where: str = "at their next episode end"
    received: list[str] = field(default_factory=list)

    def __call__(self, signum: int, frame: Any) -> None:
        name = SIGNAL_NAMES.get(signal.Signals(signum), str(signum))
        self.received.append(name)
        self.event.set()
        for child in multiprocessing.active_children():
            with contextlib.suppress(ProcessLookupError):
                os.kill(child.pid or 0, signal.SIGTERM)
        if len(self.received) == 1:
            print(f"\nlayered: {name}: no new run starts, and the running ones stop {self.where} with a checkpoint "
                  "(signal again to stop them at once)", file=sys.stderr, flush=True)

    def summary(self) -> str | None:
        """One line on what the stop did, or None when no signal came."""
        if not self.received:
            return None
        how = self.where if len(self.received) == 1 else "at once, from their last checkpoints"
        return f"sweep stopped by {self.received[0]}: its running runs stopped {how}; the same command resumes them"


def on_gpu(jobs: Sequence[Job]) -> bool:
    """Whether any of the jobs' learners run on a CUDA GPU of this machine."""
    import torch

    if not torch.cuda.is_available():
        return False
    recipes = {job.label: job.recipe for job in jobs}.values()
    return any(getattr(load_recipe(recipe).learner_config(i), "device", "cpu") in ("cuda", "auto")  # (a learner
               for recipe in recipes for i in range(len(recipe["layers"])))  # without a device setting runs on CPU)


def tasks(jobs: Sequence[Job], vectorize: bool) -> list[list[Job]]:
    """What one process of a sweep trains at a time: a job, or with `vectorize` a group: the seeds whose run
    directories share a folder (a setup's, or one of its groups' where `plan` cut its seeds into groups)."""
    if not vectorize:
        return [[job] for job in jobs]
    groups: dict[Path, list[Job]] = {}
    for job in jobs:
        groups.setdefault(job.out.parent, []).append(job)
    return list(groups.values())


def process_count(jobs: Sequence[Job], workers: int, vectorize: bool = False) -> int:
    """How many processes a sweep of `workers` at most runs at once (one, for a sweep with nothing to run)."""
    return max(1, min(workers, len(tasks(jobs, vectorize))))


def run_local(jobs: Sequence[Job], workers: int, vectorize: bool = False,
              threads: int | None = None) -> tuple[list[Outcome], SweepStop]:
    """Run the jobs in `workers` processes, showing progress over jobs; the outcomes, and the signals
    that stopped the sweep (if any). With `vectorize`, the seeds of each setup (or of each of its groups)
    train as one group (`run_group`), one group per process, each process given its share of the cores for its
    environments' workers (`env.workers = "auto"`), and computing on that many torch threads, or on `threads`.

    Workers run in sessions of their own, so that a Ctrl-C at the terminal reaches the sweep alone,
    which tells them what to do (see SweepStop).
    """
    outcomes = []
    bar = tqdm(total=len(jobs), desc="sweep", unit="run", file=sys.stderr,
               disable=not sys.stderr.isatty())  # (in a log file, the outcome lines alone: no carriage returns)
    context = multiprocessing.get_context("spawn")  # fresh interpreters: no torch state forked
    stop = SweepStop(context.Event(), "at their next step" if vectorize else "at their next episode end")
    before = {s: signal.signal(s, stop) for s in SIGNAL_NAMES}
    processes = process_count(jobs, workers, vectorize)
    cores = usable_cores() // processes
    try:
        with ProcessPoolExecutor(max_workers=processes, mp_context=context,
                                 initializer=_init_worker, initargs=(os.getpid(), stop.event, cores, threads)) as pool:
            # (the workers start with the sweep's signals blocked, until they are in sessions of their own: a Ctrl-C
            # at the terminal while they start reaches the sweep alone, which holds it until they are started)
            signal.pthread_sigmask(signal.SIG_BLOCK, set(SIGNAL_NAMES))
            try:
                futures = {pool.submit(run_group if vectorize else _one, task): task
                           for task in tasks(jobs, vectorize)}
            finally:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, set(SIGNAL_NAMES))
            for future in as_completed(futures):
                try:
                    done = future.result()
                except BrokenProcessPool:  # a worker killed (kill -9, out of memory), or by a Ctrl-C while starting
                    done = [_cut_short(job, stop) for job in futures[future]]
                for outcome in done:
                    outcomes.append(outcome)
                    bar.update()
                    bar.write(f"{outcome.status:>11}  {outcome.job.out}: {outcome.detail}")
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
        bar.close()
    return outcomes, stop


def _cut_short(job: Job, stop: SweepStop) -> Outcome:
    """What became of a job whose worker process ended before it told (the pool then stops every worker): stopped,
    or failed where no signal came to the sweep; either way the same command continues it."""
    if stop.received:
        return Outcome(job, "stopped", f"by {stop.received[0]}, as its worker was starting or at once")
    return Outcome(job, "failed", "a worker process of the sweep ended unexpectedly (killed, or out of memory?); "
                                  "the same command continues it from its last checkpoint")


def _init_worker(sweep_pid: int, stop: Any, cores: int, threads: int | None = None) -> None:
    """A worker with its share of the `cores`, on which its runs and groups compute (on `threads` torch threads
    where given), in a session of its own; and the worker ends when the sweep process is gone.

    Without the watch, killing the sweep (not its process group) would leave workers training
    on in the background, writing into run directories nobody is waiting for.
    """
    global _STOP, _THREADS
    _STOP, _THREADS = stop, threads
    os.setsid()
    for s in SIGNAL_NAMES:  # between runs, the sweep's signals are for runs that are not started: nothing to stop
        signal.signal(s, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, set(SIGNAL_NAMES))  # (blocked while it started: see run_local)
    os.environ["OMP_NUM_THREADS"] = "1"  # for the processes it starts (a group's environment workers)
    share_cores(cores)
    threading.Thread(target=_exit_when_orphaned, args=(sweep_pid,), daemon=True).start()


def _exit_when_orphaned(sweep_pid: int, every: float = 1.0) -> None:
    while os.getppid() == sweep_pid:
        time.sleep(every)
    os._exit(1)  # checkpoints are written atomically, so a run stopped here resumes cleanly


def _pack(run_dir: Path) -> dict[str, bytes]:
    """Every file of a run directory, checkpoints included, keyed by relative path."""
    if not run_dir.exists():
        return {}
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in sorted(run_dir.rglob("*")) if p.is_file()}


def _unpack(files: dict[str, bytes], run_dir: Path) -> None:
    for relative, content in files.items():
        target = run_dir / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(content)


def _run_remote(job: Job, files: dict[str, bytes]) -> tuple[Outcome, dict[str, bytes]]:
    """A Ray task: continue the job from the run's `files` (empty: from the start) in a scratch
    directory of whichever machine runs it, and return the run's files."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="layered-") as scratch:
        remote_job = Job(job.recipe, Path(scratch) / "run", job.label, job.max_steps, job.plugins)
        _unpack(files, remote_job.out)
        outcome = run_job(remote_job)
        files = _pack(remote_job.out)
    return Outcome(job, outcome.status, outcome.detail.replace(str(remote_job.out), str(job.out))), files


def run_ray(jobs: Sequence[Job], address: str | None = None) -> list[Outcome]:
    """Run the unfinished jobs as Ray tasks (one CPU each) on the cluster at `address` (default:
    start a local one) and write each run's files into its run directory here.

    Each task gets the files its run directory holds here, so a stopped run resumes from the
    last checkpoint that came back; finished runs are skipped.
    """
    ray = start_ray(address)
    task = ray.remote(num_cpus=1)(_run_remote)
    outcomes = [_finished(j, grouped=False) for j in jobs if (j.out / "results.json").exists()]
    pending = {task.remote(j, _pack(j.out)): j for j in jobs if not (j.out / "results.json").exists()}
    bar = tqdm(total=len(jobs), initial=len(outcomes), desc="sweep (ray)", unit="run", file=sys.stderr)
    for outcome in outcomes:
        bar.write(f"{outcome.status:>7}  {outcome.job.out}: {outcome.detail}")
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        outcome, files = ray.get(done[0])
        del pending[done[0]]
        _unpack(files, outcome.job.out)
        outcomes.append(outcome)
        bar.update()
        bar.write(f"{outcome.status:>7}  {outcome.job.out}: {outcome.detail}")
    bar.close()
    return outcomes
