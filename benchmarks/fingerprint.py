"""A fingerprint of what training produces: short runs of every kind of stack, and a SHA-256 of each
file they write that a change to the code must leave as it is.

    python benchmarks/fingerprint.py runs/fingerprint-a      # trains, then prints one hash per file
    python benchmarks/fingerprint.py runs/fingerprint-b
    diff <(python benchmarks/fingerprint.py runs/fingerprint-a --hash-only) \
         <(python benchmarks/fingerprint.py runs/fingerprint-b --hash-only)

A refactoring of the stack's rules, the loop or the learners is behaviour-preserving when the two
listings match on one machine: metrics.csv, episodes.csv, results.json and every checkpoint. Floating
point differs between machines, so the hashes are compared between runs on the same one, never stored.
Each run is small (networks of 32-32, 1500 steps per phase) and one torch thread is used. `--set
learner.precision=float32` compares float32 runs on a machine where `auto` computes in bfloat16. `--group K`
trains each recipe's seeds 0 to K-1 as one group instead (the group's loop and stacked learners) and hashes
every seed's files.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
SMALL = ["learner.hidden=[32, 32]", "learner.batch_size=64", "train.warmup=100", "eval.every=500",
         "eval.episodes=2", "eval.fresh_episodes=2"]
RUNS = {  # name: recipe, overrides beyond SMALL
    "tla-c": ("pendulum/tla-c.toml", []),
    "tla-o": ("pendulum/tla-o.toml", []),
    "temporl": ("pendulum/temporl.toml", []),
    "joint-gate": ("pendulum/tla-joint.toml", ["layers.slow.warmup=40"]),
    "realtime-idp": ("inverted-double-pendulum/tla-realtime.toml", []),
    "mixed-3": ("research/pendulum-gate-over-residual-3.toml", []),
    "residual-3": ("research/pendulum-residual-3.toml", []),
}
STEPS = 1500
FILES = ("metrics.csv", "episodes.csv", "results.json")


def digests(run_dir: Path) -> dict[str, str]:
    """SHA-256 of each file of the run that the code's behaviour determines."""
    paths = [run_dir / f for f in FILES] + sorted((run_dir / "checkpoints").glob("*.pt"))
    return {str(p.relative_to(run_dir)): hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in paths}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="folder for the runs (one sub-folder per run)")
    parser.add_argument("--hash-only", action="store_true", help="hash the runs already in OUT; train nothing")
    parser.add_argument("--only", nargs="*", help="names of the runs to make (default: all)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a recipe setting for every run, e.g. learner.precision=float32 (repeatable)")
    parser.add_argument("--group", type=int, default=0, metavar="K", help="train seeds 0 to K-1 of each as a group")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from layered import load_recipe, train
    from layered.group import train_group
    from layered.group_state import seed_dirs

    for name, (recipe, extra) in RUNS.items():
        if args.only and name not in args.only:
            continue
        settings = [*SMALL, *extra, *args.set]
        run_dirs = seed_dirs(args.out / name, list(range(args.group))) if args.group else [args.out / name]
        if not args.hash_only and args.group:
            train_group([load_recipe(ROOT / "recipes" / recipe, [*settings, f"train.seed={k}"])
                         for k in range(args.group)], run_dirs, name, max_steps=STEPS, progress=False)
        elif not args.hash_only:
            train(load_recipe(ROOT / "recipes" / recipe, settings), run_dirs[0], max_steps=STEPS, progress=False,
                  label=name)
        for run_dir in run_dirs:
            for file, digest in digests(run_dir).items():
                print(f"{run_dir.relative_to(args.out)}/{file} {digest}")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
