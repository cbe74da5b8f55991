"""The `layered` command: train a recipe, evaluate a trained run."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

from layered.checkpoint import CheckpointError
from layered.recipe import RecipeError, load_recipe
from layered.report import plot_episode, results_table

EXIT_BAD_INPUT = 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="layered", description="Temporally layered control stacks.")
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser(
        "train", help="train a recipe and write a run directory",
        usage="layered train RECIPE [key=value ...] [--out DIR] [--seed S] [--steps N] [--threads T]",
        epilog="key=value pairs override recipe values, e.g. train.warmup=500 layers.fast.period=2",
    )
    tr.add_argument("recipe", help="recipe TOML file")
    tr.add_argument("--out", type=Path, help="run directory (default runs/<recipe>-s<seed>-<time>)")
    tr.add_argument("--seed", type=int, help="same as train.seed=S")
    tr.add_argument("--steps", type=int, help="cap every training phase at N environment steps")
    tr.add_argument("--threads", type=int, help="torch threads (use 1 per process when running several)")
    ev = sub.add_parser("eval", help="evaluate a trained run directory")
    ev.add_argument("run_dir", type=Path)
    ev.add_argument("--episodes", type=int, help="episodes (default: the recipe's eval.episodes)")
    ev.add_argument("--threshold", type=float, help="evaluation threshold as a fraction of max action")
    ev.add_argument("--threads", type=int, help="torch threads")
    ev.add_argument("--plot", action="store_true", help="also plot the last episode: who acted when, and the action")
    sw = sub.add_parser(
        "sweep", help="train every recipe with several seeds, in parallel processes",
        usage="layered sweep RECIPE... [key=value ...] [--seeds N] [--jobs J] [--out DIR] [--steps N]",
        epilog="finished runs are skipped and stopped ones resume; then: layered report DIR",
    )
    sw.add_argument("recipes", nargs="+", metavar="RECIPE", help="recipe files (and key=value overrides)")
    sw.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    sw.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel processes (default: cores)")
    sw.add_argument("--out", type=Path, default=Path("runs/sweep"), help="sweep directory (default runs/sweep)")
    sw.add_argument("--steps", type=int, help="cap every training phase at N environment steps")
    rep = sub.add_parser("report", help="aggregate finished runs over seeds into the paper's tables and figures")
    rep.add_argument("runs", type=Path, nargs="+", help="run directories, or folders that hold them")
    rep.add_argument("--out", type=Path, help="report directory (default runs/report-<time>)")
    return parser


def _fail(message: str) -> int:
    print(f"layered: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _train(args: argparse.Namespace) -> int:
    from layered.trainer import train

    overrides = list(args.overrides) + ([f"train.seed={args.seed}"] if args.seed is not None else [])
    recipe = load_recipe(args.recipe, overrides)
    if args.steps is not None and args.steps <= 0:
        return _fail("--steps must be a positive number of environment steps")
    out = args.out or Path("runs") / f"{Path(args.recipe).stem}-s{recipe.train.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and any(out.iterdir()):
        return _fail(f"{out} already holds a run; choose another --out")
    print(f"training {args.recipe} -> {out}", file=sys.stderr)
    source = Path(args.recipe)
    train(recipe, out, max_steps=args.steps, label=f"{source.parent.name}/{source.stem}")
    print((out / "results.md").read_text())
    print(f"run directory: {out} (results.json, metrics.csv, curves.png, checkpoints/)")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from layered.agents import make_aec_env
    from layered.evaluate import evaluate
    from layered.trainer import load_learners, phases_of

    if not (args.run_dir / "recipe.toml").exists():
        return _fail(f"{args.run_dir} is not a run directory (no recipe.toml)")
    if args.threshold is not None and args.threshold < 0:
        return _fail("--threshold must be >= 0")
    recipe = load_recipe(args.run_dir / "recipe.toml")
    learners = load_learners(recipe, args.run_dir)
    active = list(phases_of(recipe)[-1].active)
    env = make_aec_env(recipe, active=active, evaluation=True, threshold=args.threshold, record=True)
    episodes = args.episodes or recipe.eval.episodes
    result = evaluate(env, learners, episodes, recipe.train.seed + recipe.eval.seed_offset, progress=True)
    threshold = args.threshold if args.threshold is not None else "recipe"
    row = {"phase": "eval", "learn": [], "active": active, "auc": None, "threshold": threshold,
           "episodes": episodes, **result.row()}
    out = args.run_dir / "eval" / f"threshold-{threshold}-episodes-{episodes}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(row, indent=2))
    print(results_table([row]))
    print(f"written to {out}")
    if args.plot:
        png = out.with_suffix(".png")
        plot_episode(env.trace, env.possible_agents, png, f"{recipe.env.id}: last evaluation episode")
        print(f"episode plot: {png}")
    env.close()
    return 0


def _report(args: argparse.Namespace) -> int:
    from layered.report import write_report
    from layered.summary import find_runs, group

    try:
        setups = group(find_runs(args.runs))
    except FileNotFoundError as e:
        return _fail(str(e))
    out = args.out or Path("runs") / f"report-{time.strftime('%Y%m%d-%H%M%S')}"
    print(write_report(setups, out))
    print(f"report directory: {out} (report.md, summary.csv, curves.png)")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from layered.sweep import plan, run_local

    overrides = [a for a in args.recipes if "=" in a] + args.overrides
    recipes = [a for a in args.recipes if "=" not in a]
    if args.seeds <= 0 or args.jobs <= 0 or (args.steps is not None and args.steps <= 0):
        return _fail("--seeds, --jobs and --steps must be positive")
    jobs = plan(recipes, args.seeds, args.out, overrides, args.steps)
    outcomes = run_local(jobs, args.jobs)
    failed = [o for o in outcomes if o.status == "failed"]
    print(f"{len(outcomes) - len(failed)} of {len(jobs)} runs finished in {args.out}; "
          f"tables and figures: layered report {args.out}")
    return 1 if failed else 0


COMMANDS = {"train": _train, "eval": _eval, "sweep": _sweep, "report": _report}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns 2 on bad input with one line per problem and no traceback."""
    parser = _parser()
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if a.startswith("-") or "=" not in a or args.command not in ("train", "sweep")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.overrides = extra
    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)
    try:
        return COMMANDS[args.command](args)
    except RecipeError as e:
        for line in e.lines:
            print(f"layered: error: {line}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except CheckpointError as e:
        return _fail(str(e))


if __name__ == "__main__":
    sys.exit(main())
