"""TD3 training speed of `layered` on a GPU: eager, compiled and CUDA graphs, and seeds sharing it.

Three parts, each printing a markdown table, on the benchmark's TD3 recipe (`--env`, default
Pendulum-v1; `--hidden`, default 400-300; batch 256):

* **modes**: one seed with `learner.compile` off (eager), `inductor` and `cudagraphs`, each its own
  process. Steps/s are counted over the updates after the first `--settle` (compilation and
  CUDA-graph recording happen there; their time is reported apart).
* **sweep**: `layered sweep --jobs N --device cuda` with N seeds at once, for each N of `--jobs`,
  with `--no-mps` (the processes take turns on the GPU) and under CUDA MPS (which the sweep starts
  where it can); per-seed steps/s are read from each run's train.log (the rate between
  evaluations, the first interval left out), and their sum is the aggregate.
* **group**: `layered train --seeds K --device cuda`, K seeds as one computation in one process, for
  each K of `--groups`, its update eager and captured as CUDA graphs (`--group-modes`), its
  environments stepped in the training process or in worker processes (`--group-workers`), on the
  benchmark's recipe or on `--group-recipe` (with `--set` settings); the rate of its progress
  lines times K is the aggregate.

    python benchmarks/gpu.py                                                  # all three, on the GPU
    python benchmarks/gpu.py --env HalfCheetah-v5 --hidden 256,256 --parts modes,group --groups 1
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 1,4,16,32,64
    python benchmarks/gpu.py --env Hopper-v5 --parts group --groups 32 --group-workers 0,auto
    python benchmarks/gpu.py --parts group --groups 32 --group-recipe recipes/hopper/tla-realtime.toml \
        --set layers.slow.warmup=500 --set layers.fast.warmup=1000
    python benchmarks/gpu.py --device cpu --modes off,inductor --jobs 1,2 --groups 1,2 --group-modes off --steps 1500

The last runs on a CPU (without `cudagraphs`), to check the script itself.
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

RECIPE: dict[str, Any] = {
    "env": {"id": "Pendulum-v1"},
    "layers": [{"name": "td3", "period": 1}],
    "learner": {"kind": "td3", "hidden": [400, 300], "batch_size": 256},
    "eval": {"episodes": 1, "fresh_episodes": 0},
}
RATE = re.compile(r"step (\d+)/\d+, eval return .*, (\d+) steps/s")


def td3_recipe(env: str, hidden: str, steps: int, warmup: int, every: int, **learner: str) -> dict[str, Any]:
    """The benchmark's TD3 recipe on `env` with `hidden` layer widths ("400,300"), as a dict."""
    return {**RECIPE, "env": {"id": env},
            "learner": {**RECIPE["learner"], "hidden": [int(h) for h in hidden.split(",")], **learner},
            "train": {"steps_per_phase": steps, "warmup": warmup}, "eval": {**RECIPE["eval"], "every": every}}


def one_seed(device: str, mode: str, env: str, hidden: str, steps: int, warmup: int, settle: int) -> dict[str, Any]:
    """Train one TD3 seed in this process; update times before and after the first `settle` updates."""
    import torch

    import layered
    from layered.learners.td3 import TD3

    torch.set_num_threads(1)  # as `layered sweep` runs each seed
    stamps: list[float] = []
    update = TD3.update

    def timed(self: TD3) -> Any:
        out = update(self)
        stamps.append(time.perf_counter())
        return out

    TD3.update = timed  # type: ignore[method-assign]
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


def sweep(device: str, jobs: int, env: str, hidden: str, steps: int, warmup: int, mps: bool) -> dict[str, Any]:
    """`layered sweep` with `jobs` seeds at once, under CUDA MPS (which the sweep starts where it can) or
    with `--no-mps`; per-seed steps/s from each run's train.log."""
    with tempfile.TemporaryDirectory() as tmp:
        recipe = Path(tmp) / "td3.toml"
        recipe.write_text(tomli_w.dumps(td3_recipe(env, hidden, steps, warmup, max(steps // 6, 1))))
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "layered.cli", "sweep", str(recipe), "--seeds", str(jobs), "--jobs",
                        str(jobs), "--device", device, "--out", str(Path(tmp) / "runs"),
                        *([] if mps else ["--no-mps"])], check=True, capture_output=True)
        wall = time.perf_counter() - start
        rates = []
        for log in sorted(Path(tmp, "runs").rglob("train.log")):
            intervals = [int(m.group(2)) for m in RATE.finditer(log.read_text())]
            rates.append(statistics.median(intervals[1:] or intervals))
    return {"jobs": jobs, "per_seed": rates, "aggregate": sum(rates), "wall_seconds": wall}


def group(device: str, seeds: int, recipe: str | None, env: str, hidden: str, steps: int, warmup: int, mode: str,
          workers: str, settings: list[str]) -> dict[str, Any]:
    """`layered train --seeds` with `seeds` seeds as one group, its update as `mode` (learner.compile), its
    environments stepped by `workers` processes (env.workers), of
    `recipe` (a file, with `settings`) or the benchmark's TD3 recipe; its steps/s (per seed, every seed
    stepping at once) from the progress lines, the first interval left out, times the seeds."""
    with tempfile.TemporaryDirectory() as tmp:
        if recipe is None:
            recipe = str(Path(tmp) / "td3.toml")
            Path(recipe).write_text(tomli_w.dumps(td3_recipe(env, hidden, steps, warmup, max(steps // 6, 1))))
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "layered.cli", "train", recipe, "--seeds", str(seeds),
                               "--steps", str(steps), "--device", device, "--out", str(Path(tmp) / "runs"),
                               f"learner.compile={mode}", f"env.workers={workers}", *settings],
                              capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"group of {seeds} failed: {proc.stderr.strip().splitlines()[-1]}")
        intervals = [int(m.group(2)) for m in RATE.finditer(proc.stderr)]
        rate = statistics.median(intervals[1:] or intervals)
    return {"seeds": seeds, "per_seed": rate, "aggregate": rate * seeds, "wall_seconds": wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="cuda (default) or cpu for a dry run")
    parser.add_argument("--modes", default="off,inductor,cudagraphs", help="learner.compile values to time")
    parser.add_argument("--jobs", default="1,4,8", help="seeds sharing the device at once, comma-separated")
    parser.add_argument("--steps", type=int, default=6000, help="environment steps per run (default 6000)")
    parser.add_argument("--warmup", type=int, default=1000, help="random steps before updates (default 1000)")
    parser.add_argument("--settle", type=int, default=200, help="updates left out of the rate (default 200)")
    parser.add_argument("--groups", default="1,4,16,64", help="seeds trained as one group, comma-separated")
    parser.add_argument("--env", default="Pendulum-v1", help="the benchmark recipe's environment (e.g. Hopper-v5)")
    parser.add_argument("--hidden", default="400,300", help="its hidden layer widths (e.g. 256,256)")
    parser.add_argument("--group-recipe", help="a recipe file for the group part instead (e.g. a real-time TLA one)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of the group part's recipe file (repeatable, e.g. layers.slow.warmup=500)")
    parser.add_argument("--group-modes", default="off,cudagraphs",
                        help="learner.compile values of the group part: eager, and the update as CUDA graphs")
    parser.add_argument("--group-workers", default="auto",
                        help="env.workers values of the group part (0,auto: in the training process, and in workers)")
    parser.add_argument("--parts", default="modes,sweep,group", help="which parts to run (default all three)")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(one_seed(args.device, args.child[0], args.env, args.hidden, args.steps, args.warmup,
                                  int(args.child[1]))))
        return
    import torch

    where = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {os.cpu_count()} cores"
    print(f"TD3 ({args.hidden}) on {args.env}, {args.steps} steps per run ({args.warmup} random), "
          f"torch {torch.__version__}, {where}")
    if "modes" in args.parts:
        print("\n| learner.compile | steps/s after settling | first updates (s) | wall s |\n|---|---|---|---|")
        for mode in args.modes.split(","):
            proc = subprocess.run([sys.executable, __file__, "--child", mode, str(args.settle), "--device", args.device,
                                   "--steps", str(args.steps), "--warmup", str(args.warmup), "--env", args.env,
                                   "--hidden", args.hidden],
                                  capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                print(f"| {mode} | failed: {proc.stderr.strip().splitlines()[-1]} | | |", flush=True)
                continue
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            print(f"| {mode} | {row['steps_per_second']:.1f} | {row['settle_seconds']:.1f} "
                  f"| {row['wall_seconds']:.1f} |", flush=True)
    if "sweep" in args.parts:
        print("\n| seeds at once | CUDA MPS | aggregate steps/s | per seed steps/s | wall s |\n|---|---|---|---|---|")
        for jobs in map(int, args.jobs.split(",")):
            for mps in (False, True) if jobs > 1 else (False,):
                row = sweep(args.device, jobs, args.env, args.hidden, args.steps, args.warmup, mps)
                seeds = ", ".join(f"{r:.0f}" for r in row["per_seed"])
                print(f"| {jobs} | {'yes' if mps else 'no'} | {row['aggregate']:.0f} | {seeds} | "
                      f"{row['wall_seconds']:.1f} |", flush=True)
    if "group" in args.parts:
        print(f"\n{args.group_recipe or args.env}, seeds as one group (layered train --seeds K)\n\n"
              "| K | learner.compile | env.workers | aggregate steps/s | per seed steps/s | wall s |\n"
              "|---|---|---|---|---|---|")
        for k in map(int, args.groups.split(",")):
            for mode in args.group_modes.split(","):
                for workers in args.group_workers.split(","):
                    row = group(args.device, k, args.group_recipe, args.env, args.hidden, args.steps, args.warmup,
                                mode, workers, args.set)
                    print(f"| {k} | {mode} | {workers} | {row['aggregate']:.0f} | {row['per_seed']:.0f} | "
                          f"{row['wall_seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
