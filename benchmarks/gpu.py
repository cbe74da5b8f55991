"""TD3 training speed of `layered` on a GPU: eager, compiled and CUDA graphs, and seeds sharing it.

Three parts, each printing a markdown table, on the benchmark's TD3 recipe (`--env`, default
Pendulum-v1; `--hidden`, default 400-300; batch 256), or for the sweep and group parts a recipe file
(`--recipe`, with `--set` settings: a TLA-C one, say):

* **modes**: one seed with `learner.compile` off (eager), `inductor` and `cudagraphs`, each its own
  process. Steps/s are counted over the updates after the first `--settle` (compilation and
  CUDA-graph recording happen there; their time is reported apart).
* **sweep**: `layered sweep --jobs N --device cuda` with N seeds at once, for each N of `--jobs`,
  with `--no-mps` (the processes take turns on the GPU) and under CUDA MPS (which the sweep starts
  where it can), or one of them (`--mps no` or `yes`); per-seed steps/s are read from each run's
  train.log (the rate between evaluations, warm-up and the first interval with updates left out), and
  their sum is the aggregate; GPU memory per seed is the largest process's peak.
* **group**: `layered train --seeds K --device cuda`, K seeds as one computation in one process, for
  each K of `--groups`, its update eager and captured as CUDA graphs (`--group-modes`), its
  environments stepped in the training process or in worker processes, and in how many threads of each
  (`--group-workers`, `env.workers`, `env.workers:env.threads` or `env.workers:env.threads:env.wait` values, as
  `auto`, `auto:0` or `auto:0:sleep`); the rate
  of its progress lines times K is the aggregate, and its process's peak GPU memory over K the memory
  per seed. With `--splits S` the K seeds are also cut into S groups trained at once, each its own
  process pinned to its share of the cores (where a group's host work, not the GPU, sets its pace, S
  processes do S times the host work), under CUDA MPS; their rates summed are the aggregate.

GPU memory is what the driver reports per process (`nvidia-smi`, polled; the CUDA context included,
about 0.5 GB a process), so a sweep pays a context per seed and a group one in all (`device_memory.py`).

A fourth part, **targets**, measures the figures the vectorised engine is held to, each against what
it must reach, in one table: one TD3 seed on HalfCheetah-v5 with 256-256 networks (the best of the
single run's `--modes` and a group of one's, over training steps alone as LeanRL's published 936
steps/s on an H100 are, and a single run's and a group of one's `--group-modes` with their evaluations),
`--target-seeds` (32) TD3 seeds of Hopper-v5 as one group (20,000 aggregate steps/s; over training steps
alone too), and as many seeds of the real-time Hopper TLA recipe (10,000), each also as `--splits` groups at
once, the groups' environments in `--group-workers`; `--targets` picks some of the three (`cheetah`, `hopper`,
`realtime`). A failed setting is a row that says why; the others still run.

The rates of the sweep, group and targets parts are read from progress lines, and each interval between
two lines ends with an evaluation (one episode, every `--eval-every` steps of the TD3 recipe and of the
targets' real-time one; a sixth of a run by default): its time is in the rate, as a user's runs have it.
LeanRL's figure has none, so to compare with it, space the evaluations out (the fourth command below).

    python benchmarks/gpu.py --parts targets                                  # the engine's targets, measured
    python benchmarks/gpu.py --parts targets --targets hopper,realtime --splits 1,2   # those not met yet
    python benchmarks/gpu.py                                                  # the three parts, on the GPU
    python benchmarks/gpu.py --env HalfCheetah-v5 --hidden 256,256 --parts modes,group --groups 1
    python benchmarks/gpu.py --env HalfCheetah-v5 --hidden 256,256 --parts group --groups 1 --group-modes cudagraphs \
        --group-workers 0 --steps 16000 --eval-every 5000
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 1,4,16,32,64
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 32 --group-workers 0,auto
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 32 --group-modes cudagraphs \
        --group-workers auto,auto:2,0:1,0:8,16
    python benchmarks/gpu.py --parts targets --targets hopper --group-workers auto:auto:sleep,auto:auto:spin
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 32 --splits 1,2,4 --group-modes cudagraphs
    python benchmarks/gpu.py --parts group --groups 32 --recipe recipes/hopper/tla-realtime.toml \
        --set layers.slow.warmup=500 --set layers.fast.warmup=1000
    python benchmarks/gpu.py --parts sweep,group --jobs 4,16 --groups 1,4,16,64 --recipe recipes/pendulum/tla-c.toml \
        --set layers.slow.warmup=250 --set layers.fast.warmup=500 --set eval.every=500 --set eval.episodes=1 \
        --set eval.fresh_episodes=0 --steps 3000
    python benchmarks/gpu.py --device cpu --modes off,inductor --jobs 1,2 --groups 1,2 --splits 1,2 --group-modes off \
        --steps 1500
    python benchmarks/gpu.py --device cpu --parts targets --modes off --group-modes off --target-seeds 2 --steps 1500

The last two run on a CPU (without `cudagraphs`), to check the script itself.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import tomli_w
from device_memory import DeviceMemory, mib
from group_split import groups_at_once

RECIPE: dict[str, Any] = {
    "env": {"id": "Pendulum-v1"},
    "layers": [{"name": "td3", "period": 1}],
    "learner": {"kind": "td3", "hidden": [400, 300], "batch_size": 256},
    "eval": {"episodes": 1, "fresh_episodes": 0},
}
# a progress line (`layered.progress`): "<phase>: step S/T, eval return R ± D, N steps/s[ per seed (M in all)]
# [, warm-up][, about T left[ in this phase, then ...]]"
RATE = re.compile(r"^(.*): step \d+/\d+, eval return [^,]*, (\d+) steps/s(?: per seed \(\d+ in all\))?(, warm-up)?"
                  r"(?:, about .* left.*)?$", re.MULTILINE)
ROOT = Path(__file__).resolve().parent.parent
REALTIME_TLA = ROOT / "recipes/hopper/tla-realtime.toml"
REALTIME_WARMUP = ["layers.slow.warmup=500", "layers.fast.warmup=1000"]  # the recipe's 10k and 20k, cut to the run


class Failed(RuntimeError):
    """A measured command failed (its last line of errors is the message)."""


def td3_recipe(env: str, hidden: str, steps: int, warmup: int, every: int, **learner: str) -> dict[str, Any]:
    """The benchmark's TD3 recipe on `env` with `hidden` layer widths ("400,300"), as a dict."""
    return {**RECIPE, "env": {"id": env},
            "learner": {**RECIPE["learner"], "hidden": [int(h) for h in hidden.split(",")], **learner},
            "train": {"steps_per_phase": steps, "warmup": warmup}, "eval": {**RECIPE["eval"], "every": every}}


def one_seed(device: str, mode: str, env: str, hidden: str, steps: int, warmup: int, settle: int) -> dict[str, Any]:
    """Train one TD3 seed in this process; update times before and after the first `settle` updates."""
    import torch

    import layered
    from layered.learners import LEARNERS

    torch.set_num_threads(1)  # as `layered sweep` runs each seed
    stamps: list[float] = []
    learner = LEARNERS.get("td3")  # (with `cudagraphs` on a GPU, it trains as a group of one)
    update = learner.update

    def timed(self: Any) -> Any:
        out = update(self)
        stamps.append(time.perf_counter())
        return out

    learner.update = timed  # type: ignore[method-assign]
    recipe = layered.load_recipe(td3_recipe(env, hidden, steps, warmup, 10 * steps, device=device, compile=mode))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        layered.train(recipe, out, progress=False)
    if len(stamps) <= settle + 1:
        raise SystemExit(f"only {len(stamps)} updates: raise --steps above the warm-up plus --settle")
    first = stamps[0] - (stamps[1] - stamps[0])  # the first update's start, near enough
    return {"mode": mode, "settle_seconds": stamps[settle] - first,
            "steps_per_second": (len(stamps) - 1 - settle) / (stamps[-1] - stamps[settle]),
            "wall_seconds": time.perf_counter() - start}


def sweep(device: str, jobs: int, recipe: str | None, env: str, hidden: str, steps: int, warmup: int, every: int,
          mps: bool, settings: list[str]) -> dict[str, Any]:
    """`layered sweep` with `jobs` seeds at once of `recipe` (a file, with `settings`) or the benchmark's TD3 recipe,
    under CUDA MPS (which the sweep starts where it can) or with `--no-mps`; per-seed steps/s from each run's
    train.log, and the largest process's peak GPU memory."""
    with tempfile.TemporaryDirectory() as tmp:
        recipe = recipe or _td3_file(tmp, env, hidden, steps, warmup, every)
        start = time.perf_counter()
        with DeviceMemory() as memory:
            subprocess.run([sys.executable, "-m", "layered.cli", "sweep", recipe, "--seeds", str(jobs), "--jobs",
                            str(jobs), "--steps", str(steps), "--device", device, "--out", str(Path(tmp) / "runs"),
                            *settings, *([] if mps else ["--no-mps"])], check=True, capture_output=True)
        wall = time.perf_counter() - start
        rates = []
        for log in sorted(Path(tmp, "runs").rglob("train.log")):
            rates.append(settled_rate(log.read_text()))
    return {"jobs": jobs, "per_seed": rates, "aggregate": sum(rates), "wall_seconds": wall,
            "mib_per_seed": memory.largest()}


def _td3_file(folder: str, env: str, hidden: str, steps: int, warmup: int, every: int) -> str:
    """The benchmark's TD3 recipe written as a file in `folder`; its path."""
    path = Path(folder) / "td3.toml"
    path.write_text(tomli_w.dumps(td3_recipe(env, hidden, steps, warmup, every)))
    return str(path)


def group(device: str, seeds: int, recipe: str | None, env: str, hidden: str, steps: int, warmup: int, every: int,
          mode: str, workers: str, settings: list[str], splits: int = 1, single: bool = False) -> dict[str, Any]:
    """`layered train --seeds` with `seeds` seeds as one group (with `single`, one seed as a single run), its
    update as `mode` (learner.compile), its environments stepped as `workers` says (`environment_settings`), of
    `recipe` (a file, with `settings`) or the benchmark's TD3 recipe (evaluated `every` steps); its steps/s (per
    seed, every seed stepping at once) from the progress lines (as `settled_rate` reads them), times the seeds,
    and its peak GPU memory per seed. With `splits`, the seeds are cut into that many groups trained at once,
    each `layered train --seeds` process on its own share of the cores (so that `auto` sizes its workers to the
    share), under CUDA MPS on a GPU (started where it can be); the aggregate is the sum of the groups'."""
    from layered.cuda_mps import shared_gpu

    parts = groups_at_once(seeds, splits)
    with tempfile.TemporaryDirectory() as tmp:
        recipe = recipe or _td3_file(tmp, env, hidden, steps, warmup, every)
        logs = [Path(tmp) / f"group{j}.log" for j in range(splits)]
        start = time.perf_counter()
        with shared_gpu(splits if device == "cuda" else 1), DeviceMemory() as memory:
            processes = []
            for (part, share), log in zip(parts, logs, strict=True):
                with log.open("w") as err:
                    processes.append(subprocess.Popen(
                        [sys.executable, "-m", "layered.cli", "train", recipe,
                         *([] if single else ["--seeds", f"{part[0]}-{part[-1]}"]), "--steps", str(steps),
                         "--device", device, "--out", str(Path(tmp) / f"runs{part[0]}"),
                         *(["--threads", str(len(share))] if splits > 1 else []), f"learner.compile={mode}",
                         *environment_settings(workers), *settings],
                        stdout=subprocess.DEVNULL, stderr=err, text=True,
                        preexec_fn=(lambda share=share: os.sched_setaffinity(0, share)) if splits > 1 else None))
            codes = [process.wait() for process in processes]
        wall = time.perf_counter() - start
        for code, log in zip(codes, logs, strict=True):
            if code != 0:
                raise Failed(f"group of {seeds} failed: {_last_line(log.read_text())}")
        rates = [settled_rate(log.read_text()) for log in logs]
    total = memory.total()
    return {"seeds": seeds, "per_seed": rates,
            "aggregate": sum(rate * len(part) for rate, (part, _) in zip(rates, parts, strict=True)),
            "wall_seconds": wall, "mib_per_seed": None if total is None else total / seeds}


def environment_values(workers: str) -> tuple[str, str, str]:
    """env.workers, env.threads and env.wait of a `--group-workers` value: `W` (its threads and its wait `auto`),
    `W:T` or `W:T:WAIT`."""
    processes, threads, wait = (*workers.split(":"), "", "")[:3]
    return processes, threads or "auto", wait or "auto"


def environment_settings(workers: str) -> list[str]:
    """The recipe settings of a `--group-workers` value (`environment_values`)."""
    return [f"env.{key}={value}" for key, value in zip(("workers", "threads", "wait"), environment_values(workers),
                                                         strict=True)]


def training_steps(device: str, env: str, hidden: str, steps: int, warmup: int, seeds: int = 1, workers: str = "0"
                   ) -> float:
    """A group's aggregate steps/s over its training steps alone (its evaluations and checkpoints beyond the run),
    timed step by step by `gpu_profile.py --window 0` in a process of its own."""
    processes, threads, wait = environment_values(workers)
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_profile.py"), "--device", device,
                           "--env", env, "--hidden", hidden, "--steps", str(steps), "--warmup", str(warmup),
                           "--seeds", str(seeds), "--workers", processes, "--env-threads", threads,
                           "--env-wait", wait, "--window", "0"],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise Failed(_last_line(proc.stderr))
    rate = re.search(r"([\d,]+) aggregate steps/s", proc.stdout)
    if rate is None:
        raise Failed(f"no rate in: {_last_line(proc.stdout)}")
    return float(rate.group(1).replace(",", ""))


def settled_rate(log: str) -> float:
    """The median steps/s of a run's progress lines, leaving out each phase's warm-up intervals (the layer
    acts at random without updating) and its first interval with updates (which starts them, and compiles)."""
    phases: dict[str, list[int]] = {}
    for m in RATE.finditer(log):
        if not m.group(3):
            phases.setdefault(m.group(1), []).append(int(m.group(2)))
    intervals = [rate for rates in phases.values() for rate in rates[1:]]
    if not intervals:
        raise Failed("too few progress lines to measure a rate: raise --steps")
    return statistics.median(intervals)


def one_seed_child(args: argparse.Namespace, mode: str, env: str, hidden: str) -> dict[str, Any]:
    """`one_seed` in a process of its own (a compiled or captured run leaves state behind in its process)."""
    proc = subprocess.run([sys.executable, __file__, "--child", mode, str(args.settle), "--device", args.device,
                           "--steps", str(args.steps), "--warmup", str(args.warmup), "--env", env, "--hidden", hidden],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise Failed(_last_line(proc.stderr))
    return json.loads(proc.stdout.strip().splitlines()[-1])


TARGETS = ("cheetah", "hopper", "realtime")


def target_names(text: str) -> list[str]:
    """`--targets`: some of TARGETS, comma-separated."""
    names = text.split(",")
    if unknown := set(names) - set(TARGETS):
        raise argparse.ArgumentTypeError(f"no target {', '.join(sorted(unknown))} (choose from {', '.join(TARGETS)})")
    return names


Row = tuple[str, str, float | str, float, float | None]


def targets(args: argparse.Namespace) -> list[Row]:
    """The engine's targets: (what, the setting measured, steps/s or why it failed, steps/s needed, GPU MiB per seed
    where a group measured it) per setting."""
    k = args.target_seeds
    rows: list[Row] = []

    def measured(what: str, setting: str, needed: float, run: Any) -> None:
        """A row of `run()`: steps/s, or a group's result (its aggregate and memory per seed)."""
        try:
            value = run()
            rate, memory = (value["aggregate"], value["mib_per_seed"]) if isinstance(value, dict) else (value, None)
            rows.append((what, setting, rate, needed, memory))
        except Failed as e:
            rows.append((what, setting, str(e), needed, None))
        print(_target_row(rows[-1]), flush=True)

    one = "one TD3 seed, HalfCheetah-v5, 256-256"
    graphed = "cudagraphs" if args.device == "cuda" else "off"  # (what gpu_profile.py trains with)
    if "cheetah" in args.targets:
        for mode in args.modes.split(","):
            measured(one, f"single run, compile {mode}, training steps alone", 936,
                     lambda mode=mode: one_seed_child(args, mode, "HalfCheetah-v5", "256,256")["steps_per_second"])
        measured(one, f"group of 1, compile {graphed}, training steps alone",
                 936, lambda: training_steps(args.device, "HalfCheetah-v5", "256,256", args.steps, args.warmup))
        for mode in args.group_modes.split(","):
            for single in (True, False):
                measured(one, f"{'single run' if single else 'group of 1'}, compile {mode}, with evaluations", 936,
                         lambda mode=mode, single=single: group(args.device, 1, None, "HalfCheetah-v5", "256,256",
                                                                args.steps, args.warmup, every(args), mode, "0", [],
                                                                single=single))
    for name, what, recipe, env, settings, needed in (
            ("hopper", f"{k} TD3 seeds of Hopper-v5, 400-300", None, "Hopper-v5", [], 20_000),
            ("realtime", f"{k} seeds of real-time Hopper TLA (2 layers)", str(REALTIME_TLA), "Hopper-v5",
             [*REALTIME_WARMUP, f"eval.every={every(args)}", "eval.episodes=1", "eval.fresh_episodes=0"],
             10_000)):
        if name not in args.targets:
            continue
        for mode in args.group_modes.split(","):
            for workers in args.group_workers.split(","):
                if recipe is None and mode == graphed:
                    measured(what, f"compile {mode}, env.workers {workers}, training steps alone", needed,
                             lambda env=env, workers=workers: training_steps(args.device, env, "400,300", args.steps,
                                                                    args.warmup, k, workers))
                for splits in map(int, args.splits.split(",")):
                    apart = ", one group" if splits == 1 else f", {splits} groups at once"
                    measured(what, f"compile {mode}, env.workers {workers}{apart}", needed,
                             lambda recipe=recipe, env=env, settings=settings, mode=mode, workers=workers,
                             splits=splits: group(args.device, k, recipe, env, "400,300", args.steps, args.warmup,
                                                  every(args), mode, workers, settings, splits))
    return rows


def print_targets(args: argparse.Namespace) -> None:
    """Measure the targets, a row per setting as it ends, then the best setting of each target against it."""
    print(f"\nThe engine's targets ({args.steps} steps per run and phase, {args.warmup} random; real-time TLA with "
          f"{', '.join(REALTIME_WARMUP)}; one evaluation episode every {every(args)} steps)\n", flush=True)
    print("| target | setting | steps/s | needed | met | GPU MiB per seed |\n|---|---|---|---|---|---|", flush=True)
    rows = targets(args)
    best: dict[str, float] = {}
    for what, _, rate, _, _ in rows:
        if not isinstance(rate, str):
            best[what] = max(best.get(what, 0.0), rate)
    print("\n| target | best steps/s | needed | met |\n|---|---|---|---|")
    for what, needed in dict.fromkeys((row[0], row[3]) for row in rows):
        value = best.get(what)
        shown = "every setting failed" if value is None else f"{value:,.0f}"
        print(f"| {what} | {shown} | {needed:,.0f} | {'yes' if value is not None and value >= needed else 'no'} |")


def _target_row(row: Row) -> str:
    what, setting, value, needed, memory = row
    if isinstance(value, str):
        return f"| {what} | {setting} | failed: {value} | {needed:,.0f} | no | |"
    return (f"| {what} | {setting} | {value:,.0f} | {needed:,.0f} | {'yes' if value >= needed else 'no'} "
            f"| {'' if memory is None else mib(memory)} |")


def every(args: argparse.Namespace) -> int:
    """Environment steps between the runs' evaluations: `--eval-every`, or a sixth of a run."""
    return args.eval_every or max(args.steps // 6, 1)


def _last_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1] if lines else "no message"


def arguments() -> argparse.ArgumentParser:
    """The benchmark's command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="cuda (default) or cpu for a dry run")
    parser.add_argument("--modes", default="off,inductor,cudagraphs", help="learner.compile values to time")
    parser.add_argument("--jobs", default="1,4,8", help="seeds sharing the device at once, comma-separated")
    parser.add_argument("--steps", type=int, default=6000, help="environment steps per run (default 6000)")
    parser.add_argument("--warmup", type=int, default=1000, help="random steps before updates (default 1000)")
    parser.add_argument("--eval-every", type=int,
                        help="steps between evaluations of one episode (default a sixth of a run), in each rate's time")
    parser.add_argument("--settle", type=int, default=200, help="updates left out of the rate (default 200)")
    parser.add_argument("--mps", default="no,yes", help="the sweep part without and with CUDA MPS (no,yes; or one)")
    parser.add_argument("--groups", default="1,4,16,64", help="seeds trained as one group, comma-separated")
    parser.add_argument("--env", default="Pendulum-v1", help="the benchmark recipe's environment (e.g. Hopper-v5)")
    parser.add_argument("--hidden", default="400,300", help="its hidden layer widths (e.g. 256,256)")
    parser.add_argument("--recipe", help="a recipe file for the sweep and group parts instead (e.g. a TLA-C one)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of the sweep and group parts' recipe (repeatable: layers.slow.warmup=500)")
    parser.add_argument("--group-modes", default="off,cudagraphs",
                        help="learner.compile values of the group part: eager, and the update as CUDA graphs")
    parser.add_argument("--group-workers", default="auto",
                        help="env.workers values of the group part (0,auto: in the training process, and in workers), "
                             "each with its env.threads and env.wait after colons if wanted (0:8, auto:2, auto:0:spin)")
    parser.add_argument("--splits", default="1",
                        help="the group part's (and the targets' Hopper groups') seeds cut into this many groups "
                             "trained at once, each a process on its share of the cores (1: one group; 1,2,4)")
    parser.add_argument("--parts", default="modes,sweep,group",
                        help="which parts to run: modes, sweep, group (the default: all three) and targets")
    parser.add_argument("--target-seeds", type=int, default=32, help="the targets' group size (default 32)")
    parser.add_argument("--targets", default=",".join(TARGETS), type=target_names,
                        help="which targets to measure: cheetah (one HalfCheetah-v5 seed), hopper (the Hopper TD3 "
                             "group), realtime (the real-time Hopper TLA group); default all three")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    return parser


def print_modes(args: argparse.Namespace) -> None:
    """One seed's rate under each `learner.compile` mode, a row each."""
    print("\n| learner.compile | steps/s after settling | first updates (s) | wall s |\n|---|---|---|---|")
    for mode in args.modes.split(","):
        try:
            row = one_seed_child(args, mode, args.env, args.hidden)
        except Failed as e:
            print(f"| {mode} | failed: {e} | | |", flush=True)
            continue
        print(f"| {mode} | {row['steps_per_second']:.1f} | {row['settle_seconds']:.1f} "
              f"| {row['wall_seconds']:.1f} |", flush=True)


def print_sweeps(args: argparse.Namespace) -> None:
    """A process per seed, at each number of seeds at once, with and without CUDA MPS."""
    print(f"\n{args.recipe or args.env}, a process per seed (layered sweep --jobs N)\n\n"
          "| seeds at once | CUDA MPS | aggregate steps/s | per seed steps/s | GPU MiB per seed | wall s |\n"
          "|---|---|---|---|---|---|")
    for jobs in map(int, args.jobs.split(",")):
        for mps in [m == "yes" for m in args.mps.split(",")] if jobs > 1 else (False,):
            row = sweep(args.device, jobs, args.recipe, args.env, args.hidden, args.steps, args.warmup,
                        every(args), mps, args.set)
            seeds = ", ".join(f"{r:.0f}" for r in row["per_seed"])
            print(f"| {jobs} | {'yes' if mps else 'no'} | {row['aggregate']:.0f} | {seeds} | "
                  f"{mib(row['mib_per_seed'])} | {row['wall_seconds']:.1f} |", flush=True)


def print_groups(args: argparse.Namespace) -> None:
    """Seeds as groups, at each group size, split, compile mode and environment-worker setting."""
    print(f"\n{args.recipe or args.env}, seeds as groups (layered train --seeds, one process per group)\n\n"
          "| K | groups at once | learner.compile | env.workers[:threads] | aggregate steps/s | per seed steps/s "
          "(each group's) | GPU MiB per seed | wall s |\n|---|---|---|---|---|---|---|---|")
    for k in map(int, args.groups.split(",")):
        for splits in (s for s in map(int, args.splits.split(",")) if s <= k):
            for mode in args.group_modes.split(","):
                for workers in args.group_workers.split(","):
                    try:
                        row = group(args.device, k, args.recipe, args.env, args.hidden, args.steps,
                                    args.warmup, every(args), mode, workers, args.set, splits)
                    except Failed as e:
                        print(f"| {k} | {splits} | {mode} | {workers} | failed: {e} | | | |", flush=True)
                        continue
                    print(f"| {k} | {splits} | {mode} | {workers} | {row['aggregate']:.0f} | "
                          f"{', '.join(f'{r:.0f}' for r in row['per_seed'])} | {mib(row['mib_per_seed'])} | "
                          f"{row['wall_seconds']:.1f} |", flush=True)


def main() -> None:
    parser = arguments()
    args = parser.parse_args()
    if args.child:
        print(json.dumps(one_seed(args.device, args.child[0], args.env, args.hidden, args.steps, args.warmup,
                                  int(args.child[1]))))
        return
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        parser.exit(2, f"gpu.py: no CUDA device here (torch {torch.__version__}); --device cpu makes a dry run\n")
    where = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {os.cpu_count()} cores"
    benchmark = "" if set(args.parts.split(",")) <= {"targets"} else (  # (the targets name their own settings)
        f"TD3 ({args.hidden}) on {args.env}, {args.steps} steps per run ({args.warmup} random), ")
    print(f"{benchmark}torch {torch.__version__}, {where}")
    parts = {"modes": print_modes, "sweep": print_sweeps, "group": print_groups, "targets": print_targets}
    for name, part in parts.items():
        if name in args.parts:
            part(args)

if __name__ == "__main__":
    main()
