"""Where a group's training step goes on a GPU: each step timed, and a `torch.profiler` window of steps.

Trains the benchmark's TD3 recipe (see `gpu.py`) as a group with its evaluations and checkpoints moved
beyond the run, so that the steps timed are training steps alone (acting, the environments' step, storing,
the update), as LeanRL's published rates are. Prints the median and 90th percentile of the time per step
over the steps with updates before the profiler's window, and the window's kernels (GPU time) and host
operations (CPU time), in tables; writes the window's trace (Chrome format, gzipped) beside them with
`--trace`. With `--window 0` nothing is profiled: the steps are timed alone (`gpu.py --parts targets`
takes a group of one's rate so). With `--pystats FILE` the training process's Python functions are profiled
(`cProfile`) over the timed steps, which it slows, and their totals written to FILE: where the host's time
goes when the host, not the GPU, sets a group's pace. With `--recipe`, a recipe of your own instead, its layers'
warm-ups set with `--set` (`--warmup` is then where its last phase's updates begin, for the timing): the steps
timed and profiled are its last phase's (a real-time TLA's fast phase, both layers acting and the fast one
learning).

    python benchmarks/gpu_profile.py                                   # one HalfCheetah-v5 seed, 256-256
    python benchmarks/gpu_profile.py --env Hopper-v5 --hidden 400,300 --seeds 32 --workers auto
    python benchmarks/gpu_profile.py --env Hopper-v5 --hidden 400,300 --seeds 32 --workers 0 --env-threads 8
    python benchmarks/gpu_profile.py --env Hopper-v5 --hidden 400,300 --seeds 32 --workers auto --env-wait sleep
    python benchmarks/gpu_profile.py --env Hopper-v5 --hidden 400,300 --seeds 32 --workers auto --window 0 \
        --pystats host.txt
    python benchmarks/gpu_profile.py --recipe recipes/hopper/tla-realtime.toml --seeds 32 --workers auto --window 0 \
        --set layers.slow.warmup=500 --set layers.fast.warmup=1000 --pystats host.txt
    python benchmarks/gpu_profile.py --device cpu --steps 1600 --window 50   # checks the script on a CPU
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import gzip
import io
import json
import pstats
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import tomli_w
import torch
from torch.profiler import ProfilerActivity, profile, schedule

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu import td3_recipe

from layered import progress
from layered.cli import main as layered


def profiled(args: argparse.Namespace, tmp: Path, host: cProfile.Profile | None = None
             ) -> tuple[list[float], torch.profiler.profile | None]:
    """Train the group; the times between its last phase's steps, and the profiler that recorded that phase's last
    `--window` steps (None for a window of none). `host`, where given, profiles the Python functions over the
    timed steps."""
    mode = "cudagraphs" if args.device == "cuda" else "off"
    if args.recipe is None:
        recipe, settings = tmp / "td3.toml", []
        recipe.write_text(tomli_w.dumps(td3_recipe(args.env, args.hidden, args.steps, args.warmup, 10 * args.steps,
                                                   compile=mode)))
    else:  # (its evaluations, and the checkpoints with them, beyond the run)
        recipe = args.recipe
        settings = ["--steps", str(args.steps), f"learner.compile={mode}", f"eval.every={10 * args.steps}", *args.set]
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if args.device == "cuda" else [])
    wait = args.steps - args.window - 20 if args.window else args.steps
    first = args.warmup + (wait - args.warmup) // 4  # (the first updates capture their graphs)
    stamps: list[float] = []
    advance = progress.Progress.advance
    window = (profile(activities=activities, schedule=schedule(wait=wait, warmup=20, active=args.window))
              if args.window else contextlib.nullcontext())
    with window as prof:
        def stepped(bar: progress.Progress, steps: int) -> None:
            advance(bar, steps)
            if bar.later:
                return  # (a phase before the last)
            if prof is not None:
                prof.step()
            stamps.append(time.perf_counter())
            if host is not None and len(stamps) in (first + 1, wait):
                (host.enable if len(stamps) == first + 1 else host.disable)()

        progress.Progress.advance = stepped  # type: ignore[method-assign,assignment]
        try:
            layered(["train", str(recipe), "--seeds", str(args.seeds), "--device", args.device,
                     "--out", str(tmp / "runs"), f"env.workers={args.workers}", f"env.threads={args.env_threads}",
                     f"env.wait={args.env_wait}", *settings])
        finally:
            progress.Progress.advance = advance  # type: ignore[method-assign]
    return [b - a for a, b in zip(stamps[first:wait], stamps[first + 1:wait], strict=False)], prof


def python_totals(host: cProfile.Profile, steps: int) -> str:
    """The profiled functions' totals over `steps` training steps, by their own time and by their cumulative time."""
    text = io.StringIO()
    print(f"{steps} training steps profiled (cProfile's own overhead included)", file=text)
    for order in ("tottime", "cumtime"):
        pstats.Stats(host, stream=text).sort_stats(order).print_stats(40)
    return text.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--recipe", type=Path, help="a recipe to time instead of the benchmark's TD3 (its last phase)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of --recipe's (repeatable)")
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--hidden", default="256,256")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--workers", default="0", help="env.workers (0: in this process; auto)")
    parser.add_argument("--env-threads", default="auto", help="env.threads (threads stepping the rows per process)")
    parser.add_argument("--env-wait", default="auto", help="env.wait (how the workers and the group wait: sleep, spin)")
    parser.add_argument("--steps", type=int, default=2400)
    parser.add_argument("--warmup", type=int, default=1000)
    parser.add_argument("--window", type=int, default=200, help="steps the profiler records, at the end (0: none)")
    parser.add_argument("--trace", type=Path, help="write the window's trace here (.json.gz)")
    parser.add_argument("--times", type=Path, help="write the timed steps' durations here (seconds, JSON)")
    parser.add_argument("--pystats", type=Path, help="profile the timed steps' Python functions; their totals here")
    args = parser.parse_args()
    host = cProfile.Profile() if args.pystats else None
    with tempfile.TemporaryDirectory() as tmp:
        gaps, prof = profiled(args, Path(tmp), host)
        if args.trace and prof is not None:
            prof.export_chrome_trace(str(Path(tmp) / "trace.json"))
            with open(Path(tmp) / "trace.json", "rb") as f, gzip.open(args.trace, "wb") as g:
                shutil.copyfileobj(f, g)
    if args.times:
        args.times.write_text(json.dumps(gaps))
    if host is not None:
        args.pystats.write_text(python_totals(host, len(gaps)))
    deciles = statistics.quantiles(gaps, n=10)
    what = f"TD3 ({args.hidden}) on {args.env}" if args.recipe is None else f"{args.recipe}, its last phase"
    print(f"\n{args.seeds} seed(s) of {what}, {args.device}: a training step took a median "
          f"of {statistics.median(gaps) * 1e3:.3f} ms (p90 {deciles[-1] * 1e3:.3f} ms) over {len(gaps)} steps, "
          f"{args.seeds / statistics.median(gaps):,.0f} aggregate steps/s\n")
    if prof is None:
        return
    table = prof.key_averages()
    if args.device == "cuda":
        print(table.table(sort_by="self_cuda_time_total", row_limit=25))
    print(table.table(sort_by="self_cpu_time_total", row_limit=25))


if __name__ == "__main__":  # (environment workers start by importing this module)
    main()
