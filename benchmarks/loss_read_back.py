"""What a group's losses cost the host at each evaluation: K seeds' TD3 losses of `--updates` updates (the
actor's at every second, as `policy_delay = 2` steps it) kept on the learner's device (`PendingLosses`), read
back into each seed's loop state (`layered.group._read_back`) and averaged into its metrics row
(`layered.results.mean_losses`). At the paper's protocol a group reads back 5000 updates per evaluation.

    python benchmarks/loss_read_back.py                          # K = 32, 5000 updates, on the CPU
    python benchmarks/loss_read_back.py --seeds 64 --device cuda

Prints the median seconds of `--repeats` read-backs and of the means that follow each.
"""

from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace

import numpy as np
import torch

from layered.group import _read_back
from layered.learners.td3_group import TD3Group
from layered.pending_losses import PendingLosses
from layered.results import mean_losses
from layered.runstate import LoopState


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=32, help="K")
    parser.add_argument("--updates", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    generator = torch.Generator(args.device).manual_seed(0)
    every, none = np.ones(args.seeds, bool), np.zeros(args.seeds, bool)
    read, means = [], []
    for _ in range(args.repeats):
        pending = PendingLosses()
        for u in range(args.updates):
            actor = u % 2 == 1
            values = {name: torch.rand(args.seeds, generator=generator, device=args.device)
                      for name in ("critic", "actor")[: 1 + actor]}
            pending.add(values, {"critic": every, "actor": every if actor else none})
        seeds = [SimpleNamespace(state=LoopState(losses={"fast": []})) for _ in range(args.seeds)]
        start = time.perf_counter()
        _read_back({"fast": pending}, {"fast": TD3Group.loss_names}, seeds, 0)  # type: ignore[arg-type]
        read.append(time.perf_counter() - start)
        start = time.perf_counter()
        for seed in seeds:
            mean_losses(seed.state.losses, {"fast": TD3Group.loss_names})
        means.append(time.perf_counter() - start)
    print(f"K = {args.seeds}, {args.updates} updates, {args.device}: read back {statistics.median(read):.3f} s, "
          f"means {statistics.median(means):.3f} s (medians of {args.repeats})")


if __name__ == "__main__":
    main()
