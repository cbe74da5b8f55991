"""Where a group's time goes: one `layered train --seeds K` in this process, its wall time split into
start-up, set-up, the environments' steps and resets, acting, updates, evaluations, checkpoints,
the losses' read-back from the device, the episodes' log rows, and the rest of the loop (the stack rules,
transitions).

    python benchmarks/group_time.py                                     # Pendulum TD3, K = 8, on CPU
    python benchmarks/group_time.py --recipe recipes/hopper/tla-realtime.toml --seeds 16
    python benchmarks/group_time.py --device cuda --seeds 64 --threads 16

Each part is timed by wrapping the loop's own methods (nothing in `layered` is changed); a call made
inside another timed part counts to the outer one (an evaluation's steps are the evaluation's), but
for the read-back of the losses, always its own part. The environments' steps are the time spent
waiting for them after the update is queued (with `--set env.workers=N` they step meanwhile). On a
GPU, acting includes copying the actions to the host and the read-back waits for the updates queued
since the last one, so those two parts are where host transfers and waiting show.
"""

from __future__ import annotations

import argparse
import functools
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

START = time.perf_counter()

import torch  # noqa: E402  (after START: imports count as start-up)

ROOT = Path(__file__).resolve().parent.parent
PARTS = ("environments: steps", "environments: resets", "acting", "updates", "losses read back", "evaluations",
         "checkpoints", "episode logs")


class Clock:
    """Seconds per part. A call inside a part already being timed adds to that part, except a part
    named `apart`, whose time is taken out of the part it is called in."""

    def __init__(self, apart: str) -> None:
        self.seconds: dict[str, float] = {}
        self.apart = apart
        self.open: list[list[float]] = []  # per timed call under way: its start, and the time taken out of it

    def wrap(self, owner: Any, name: str, part: str) -> None:
        """Time `owner.name` (a method or a module's function) as `part`."""
        inner: Callable[..., Any] = getattr(owner, name)

        @functools.wraps(inner)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self.open and part != self.apart:
                return inner(*args, **kwargs)
            self.open.append([time.perf_counter(), 0.0])
            try:
                return inner(*args, **kwargs)
            finally:
                start, taken_out = self.open.pop()
                elapsed = time.perf_counter() - start
                self.seconds[part] = self.seconds.get(part, 0.0) + elapsed - taken_out
                if self.open:
                    self.open[-1][1] += elapsed

        setattr(owner, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipe", default=str(ROOT / "recipes/pendulum/td3.toml"))
    parser.add_argument("--seeds", type=int, default=8, help="K, the seeds of the group")
    parser.add_argument("--steps", type=int, default=1500, help="base steps per phase")
    parser.add_argument("--warmup", type=int, default=500)
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a recipe setting (repeatable)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import layered.group as group_module
    from layered.env_group import EnvGroup
    from layered.env_workers import EnvWorkers
    from layered.learners.choice_group import ChoiceLearnerGroup
    from layered.learners.td3_group import TD3Group
    from layered.orders import phases_of

    clock = Clock(apart="losses read back")
    for owner, name, part in ((EnvGroup, "step_wait", "environments: steps"),
                              (EnvWorkers, "step_wait", "environments: steps"),
                              (EnvGroup, "reset", "environments: resets"),
                              (EnvWorkers, "reset", "environments: resets"),
                              (TD3Group, "act", "acting"), (ChoiceLearnerGroup, "act", "acting"),
                              (group_module.Group, "_update", "updates"),
                              (group_module.Group, "_evaluate", "evaluations"),
                              (group_module.Group, "_fresh", "evaluations"),
                              (group_module.Group, "_evaluator", "evaluations"),
                              (group_module.Group, "_checkpoint", "checkpoints"),
                              (group_module.Group, "_log_episodes", "episode logs"),
                              (group_module, "save_checkpoint", "checkpoints"),
                              (group_module, "_read_back", "losses read back")):
        clock.wrap(owner, name, part)
    settings = [f"train.warmup={args.warmup}", "eval.episodes=1", "eval.fresh_episodes=0", "eval.every=100000000",
                f"learner.device={args.device}", *args.set]
    recipes = group_module.group_recipes(args.recipe, range(args.seeds), settings)
    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"seed{k}" for k in range(args.seeds)]
        loop = {"start": 0.0, "end": 0.0}
        train = group_module.Group.train

        def timed_train(self: Any, saved: Any = None) -> None:
            loop["start"] = time.perf_counter()
            train(self, saved)
            loop["end"] = time.perf_counter()

        group_module.Group.train = timed_train  # type: ignore[method-assign]
        begun = time.perf_counter()
        group_module.train_group(recipes, outs, "benchmark", args.steps, progress=False)
        done = time.perf_counter()
    phases = len(phases_of(recipes[0]))
    in_loop = loop["end"] - loop["start"]
    parts = {"start-up (imports)": begun - START,
             "set-up and results (learners built, run directories, results written)": (done - begun) - in_loop,
             **{part: clock.seconds.get(part, 0.0) for part in PARTS},
             "the rest of the loop (stack rules, transitions)": in_loop - sum(clock.seconds.values())}
    total = done - START
    print(f"{Path(args.recipe).parent.name}/{Path(args.recipe).stem}, K = {args.seeds}, {args.steps} steps per phase "
          f"({args.warmup} random), device {args.device}, {args.threads} threads{''.join(f', {x}' for x in args.set)}"
          f", {phases} phase(s): {args.seeds * args.steps * phases / total:.0f} environment steps/s in all\n")
    print("| part | seconds | share |\n|---|---|---|")
    for part, seconds in parts.items():
        print(f"| {part} | {seconds:.1f} | {seconds / total:.0%} |")
    print(f"| whole command | {total:.1f} | 100% |")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
