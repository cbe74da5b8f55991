"""TD3 updates of K seeds: as one computation (`TD3Group`) against K single learners one after the other,
side by side in one process, on this machine.

    python benchmarks/group_update.py                       # Pendulum's shapes, 400-300, batch 256, one thread
    python benchmarks/group_update.py --obs 11 --act 3      # Hopper's shapes
    python benchmarks/group_update.py --device cuda --threads 16
    python benchmarks/group_update.py --seeds 4 --hidden 16,16     # where the update is all overhead

Each K is timed over the same number of update rounds after a warm-up, the two ways alternating
three times; the table gives the best of the three, seed-updates per second and the group's speed-up,
and the operations one group update dispatches (the mean of an update with the actor's step and one
without, views left out): with `cudagraphs` on a GPU, the kernels its captured update launches.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from gymnasium.spaces import Box
from torch.utils._python_dispatch import TorchDispatchMode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--obs", type=int, default=3)
    parser.add_argument("--act", type=int, default=1)
    parser.add_argument("--seeds", default="1,4,16,64", help="comma-separated K")
    parser.add_argument("--hidden", default="400,300", help="the networks' hidden widths, comma-separated")
    parser.add_argument("--rounds", type=int, default=20, help="updates of every seed per timing")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from layered.buffer import Transition
    from layered.heap import keep_freed_memory
    from layered.learners.td3 import TD3, TD3Config
    from layered.learners.td3_group import TD3Group
    from layered.outputs import OutputLayout

    keep_freed_memory()  # as a group's process does (layered.group)
    obs_space = Box(-1.0, 1.0, (args.obs,), np.float32)
    act_space = Box(-1.0, 1.0, (args.act,), np.float32)
    config = TD3Config(hidden=tuple(int(x) for x in args.hidden.split(",")), buffer_size=2000, device=args.device)
    rng = np.random.default_rng(0)
    print("| K | K single learners, seed-updates/s | one group, seed-updates/s | group speed-up | group operations "
          "per update |\n|---|---|---|---|---|")
    for k in (int(x) for x in args.seeds.split(",")):
        singles = [TD3(obs_space, act_space, OutputLayout(args.act), config, seed) for seed in range(k)]
        group = TD3Group([TD3(obs_space, act_space, OutputLayout(args.act), config, seed) for seed in range(k)])
        for _ in range(1000):
            obs = rng.uniform(-1, 1, (k, args.obs)).astype(np.float32)
            action = rng.uniform(-1, 1, (k, args.act)).astype(np.float32)
            reward = rng.normal(size=k)
            group.observe(obs, action, reward, obs, np.zeros(k, bool), np.full(k, 0.99))
            for s, single in enumerate(singles):
                single.observe(Transition(obs[s], action[s], float(reward[s]), obs[s], False, 0.99))

        ways = {"singly": [single.update for single in singles], "together": [group.update]}
        best = dict.fromkeys(ways, float("inf"))
        for updates in ways.values():  # warm-up
            for update in updates:
                update()
        for _ in range(3):
            for way, updates in ways.items():
                best[way] = min(best[way], timed(updates, args.rounds, args.device))
        rate = {way: k * args.rounds / seconds for way, seconds in best.items()}
        print(f"| {k} | {rate['singly']:.0f} | {rate['together']:.0f} | {rate['together'] / rate['singly']:.2f}x "
              f"| {operations(group.update):.1f} |", flush=True)


class Operations(TorchDispatchMode):
    """Counts the operations dispatched while it is on, views left out."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        self.count += not func.is_view
        return func(*args, **(kwargs or {}))


def operations(update: Callable[[], object]) -> float:
    """Operations per call of a TD3 group's `update`, over two calls (with and without the actor's step)."""
    counter = Operations()
    with counter:
        update()
        update()
    return counter.count / 2


def timed(updates: list, rounds: int, device: str) -> float:
    """Seconds for `rounds` rounds of the `updates` (each a call), the device's queue drained at both ends."""
    if device == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(rounds):
        for update in updates:
            update()
    if device == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
