"""What a single run's evaluation costs: its episodes played one after another through the agent view (as
`layered eval` plays them) against side by side, as the training loop now plays them (`evaluate_run`), on
the same learners and the same episodes, in one process, alternating.

    python benchmarks/run_evaluation.py                                       # Pendulum TLA-C, untrained
    python benchmarks/run_evaluation.py --recipe hopper/td3-realtime.toml --set env.id=HalfCheetah-v5
    python benchmarks/run_evaluation.py --run runs/RUN                        # a trained run's weights

Prints the best of `--repeats` timings of each way, their ratio, and how far apart their mean returns are.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import layered
from layered.agents import make_aec_env
from layered.evaluate import evaluate
from layered.group_eval import evaluate_run, open_run_evaluator
from layered.learner_set import build_learners
from layered.run_evals import open_run
from layered.orders import phases_of

RECIPES = Path(__file__).resolve().parent.parent / "recipes"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", default="pendulum/tla-c.toml", help="a shipped recipe (untrained learners)")
    parser.add_argument("--set", action="append", default=[], help="a recipe setting (repeatable)")
    parser.add_argument("--run", type=Path, help="evaluate this run directory's final weights instead")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.run is not None:
        run = open_run(args.run, "final")
        recipe, learners, active = run.recipe, run.learners, run.active
    else:
        recipe = layered.load_recipe(RECIPES / args.recipe, args.set)
        learners, active = build_learners(recipe), list(phases_of(recipe)[-1].active)
    env = make_aec_env(recipe, active=active, evaluation=True, keep_trace=True)
    evaluator = open_run_evaluator(recipe, active, args.episodes)
    seconds: dict[str, list[float]] = {"one after another": [], "side by side": []}
    try:
        for _ in range(args.repeats):
            start = time.perf_counter()
            alone = evaluate(env, learners, args.episodes, 100)
            seconds["one after another"].append(time.perf_counter() - start)
            start = time.perf_counter()
            together = evaluate_run(evaluator, learners, args.episodes, 100)
            seconds["side by side"].append(time.perf_counter() - start)
    finally:
        env.close()
        evaluator[2].close()
    steps = alone.steps * args.episodes
    label = args.run or f"{recipe.env.id} {args.recipe}"
    print(f"{label}: {args.episodes} episodes, {steps:.0f} steps, {evaluator[1].rows} side by side, one thread")
    print(f"| way | seconds (best of {args.repeats}) | µs per step |\n|---|---|---|")
    for way, times in seconds.items():
        print(f"| {way} | {min(times):.3f} | {min(times) / steps * 1e6:.0f} |")
    ratio = min(seconds["one after another"]) / min(seconds["side by side"])
    print(f"side by side is {ratio:.2f}x as fast; mean returns {alone.return_mean:.6f} and {together.return_mean:.6f}")


if __name__ == "__main__":
    main()
