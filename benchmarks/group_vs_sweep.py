"""K seeds of one recipe: as one group (`layered train --seeds`) against `layered sweep --jobs J`, side by side.

For each K, both commands train the same seeds for `--steps` base steps per phase, evaluations cut
to one episode at the end of each phase; each is its own process tree, timed from start to end, and
the two alternate `--repeats` times. The table gives aggregate environment steps per second (K x
steps x phases / wall time, best of the repeats) and the peak memory per seed (the group's process
divided by K; a sweep's largest worker). With `--splits S`, a third way alternates with them: the K
seeds cut into S groups trained at once, each `layered train --seeds` on one S-th of the cores (pinned
with `taskset`, its torch threads as many), its memory per seed its largest process's over its seeds.

    python benchmarks/group_vs_sweep.py                                   # Pendulum TD3, K = 1, 4, 8, on CPU
    python benchmarks/group_vs_sweep.py --recipe recipes/pendulum/tla-c.toml --seeds 4
    python benchmarks/group_vs_sweep.py --seeds 8 --set learner.precision=bfloat16
    python benchmarks/group_vs_sweep.py --seeds 8 --splits 2                   # and as 2 groups of 4 at once
    python benchmarks/group_vs_sweep.py --recipe recipes/hopper/td3-realtime.toml --device cuda --seeds 1,4,16,64
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from group_split import groups_at_once

ROOT = Path(__file__).resolve().parent.parent
MEASURE = """
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, code)
"""


def timed(command: list[str]) -> tuple[float, float]:
    """Wall seconds of `command` and the peak resident memory (MiB) of its largest process."""
    out = subprocess.run([sys.executable, "-c", MEASURE, *command], capture_output=True, text=True, check=True)
    wall, rss, code = out.stdout.split()
    if code != "0":
        raise SystemExit(f"failed ({code}): {' '.join(command)}")
    return float(wall), float(rss) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipe", default=str(ROOT / "recipes/pendulum/td3.toml"))
    parser.add_argument("--seeds", default="1,4,8", help="comma-separated K")
    parser.add_argument("--steps", type=int, default=1500, help="base steps per phase")
    parser.add_argument("--warmup", type=int, default=500)
    parser.add_argument("--jobs", type=int, default=2, help="the sweep's processes (one torch thread each)")
    parser.add_argument("--threads", type=int, default=2, help="the group's torch threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--splits", type=int, default=1, help="also the seeds as this many groups at once (2 or more)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a recipe setting for both sides, e.g. learner.precision=bfloat16 (repeatable)")
    args = parser.parse_args()
    layered = str(Path(sys.executable).with_name("layered"))
    settings = [f"train.warmup={args.warmup}", "eval.episodes=1", "eval.fresh_episodes=0", "eval.every=100000000",
                f"learner.device={args.device}", *args.set]
    phases = _phases(args.recipe)
    print(f"{Path(args.recipe).parent.name}/{Path(args.recipe).stem}, {args.steps} steps x {phases} phases per seed, "
          f"device {args.device}{''.join(f', {x}' for x in args.set)}; group: {args.threads} threads; sweep: "
          f"--jobs {args.jobs}, 1 thread each\n")
    split = args.splits > 1
    print(f"| K | group, steps/s | sweep, steps/s | group / sweep |{' groups at once, steps/s | / sweep |' * split}"
          f" MiB per seed: group / sweep{' / groups at once' * split} |")
    print(f"|---|---|---|---|{'---|---|' * split}---|")
    for k in (int(x) for x in args.seeds.split(",")):
        best = {name: (float("inf"), 0.0) for name in ("group", "sweep", "split")}
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as tmp:
                group = [layered, "train", args.recipe, "--seeds", str(k), "--steps", str(args.steps), "--threads",
                         str(args.threads), "--out", f"{tmp}/group", *settings]
                sweep = [layered, "sweep", args.recipe, "--seeds", str(k), "--jobs", str(min(args.jobs, k)),
                         "--steps", str(args.steps), "--out", f"{tmp}/sweep", *settings]
                ways = {"group": (group, k), "sweep": (sweep, 1)}
                if split:
                    ways["split"] = (["sh", "-c", split_command(layered, args, k, settings, tmp)], k / args.splits)
                for name, (command, per) in ways.items():
                    wall, rss = timed(command)
                    best[name] = min(best[name], (wall, rss / per))
        rate = {name: k * args.steps * phases / wall for name, (wall, _) in best.items()}
        ratios = f" {rate['split']:.0f} | {rate['split'] / rate['sweep']:.2f}x |" if split else ""
        memory = " / ".join(f"{best[name][1]:.0f}" for name in ("group", "sweep", "split")[: 2 + split])
        print(f"| {k} | {rate['group']:.0f} | {rate['sweep']:.0f} | {rate['group'] / rate['sweep']:.2f}x |{ratios} "
              f"{memory} |", flush=True)


def split_command(layered: str, args: argparse.Namespace, k: int, settings: list[str], tmp: str) -> str:
    """A shell command that trains the K seeds as `args.splits` groups at once, each pinned to its share of the
    cores with as many torch threads, and waits for them all (failing if one fails)."""
    lines = []
    for j, (seeds, share) in enumerate(groups_at_once(k, args.splits)):
        command = ["taskset", "-c", ",".join(map(str, share)), layered, "train", args.recipe, "--seeds",
                   f"{seeds[0]}-{seeds[-1]}", "--steps", str(args.steps), "--threads", str(len(share)), "--out",
                   f"{tmp}/split{j}", *settings]
        lines.append(f"{shlex.join(command)} & p{j}=$!")
    waits = " && ".join(f"wait $p{j}" for j in range(args.splits))
    return "; ".join(lines) + f"; {waits}"


def _phases(recipe: str) -> int:
    """How many phases the recipe trains."""
    code = (f"from layered.recipe import load_recipe; from layered.orders import phases_of; "
            f"print(len(phases_of(load_recipe({recipe!r}))))")
    return json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                     check=True).stdout)


if __name__ == "__main__":
    main()
