"""What a group's checkpoint costs as its replay buffers fill: K TD3 seeds (Hopper's shapes, 400-300) whose
buffers hold `--rows` transitions each, then `--every` more per seed before each of `--checkpoints`
checkpoints, each seed holding its phase's best weights. Three ways, side by side in the same process:
the group's (its replay as segments, `layered.replay_journal`: only the rows new since the last
checkpoint; a seed's best weights written only when they changed, `layered.best_journal`, here in a
`--best-share` of the seeds at each checkpoint), the segments with every seed's best weights in the
checkpoint file (as a group checkpointed before the best weights' files), and the whole filled buffer
with them (before the segments).

    python benchmarks/group_checkpoint.py                                # K = 32, 100k rows per seed
    python benchmarks/group_checkpoint.py --rows 1000000 --seeds 8       # the paper's 1M per seed
    python benchmarks/group_checkpoint.py --device cuda --rows 1000000 --seeds 32

The table gives, per way, the mean seconds and megabytes written per checkpoint (the learners' state,
which all write, included) and the speed-ups; the ways alternate, checkpoint by checkpoint. The default
share, 0.34, is how often an evaluation set a new best in 30 phases of 10 to 21 evaluations of this
project's runs (a checkpoint follows each evaluation by default); over longer phases it is less.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium.spaces import Box


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=32, help="K")
    parser.add_argument("--rows", type=int, default=100_000, help="transitions per seed stored before the first")
    parser.add_argument("--every", type=int, default=5000,
                        help="transitions per seed stored between checkpoints (eval.every's default)")
    parser.add_argument("--checkpoints", type=int, default=3)
    parser.add_argument("--obs", type=int, default=11)
    parser.add_argument("--act", type=int, default=3)
    parser.add_argument("--best-share", type=float, default=0.34,
                        help="share of the seeds whose best weights changed since the last checkpoint")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from layered.best_journal import BestJournal
    from layered.checkpoint import save_checkpoint
    from layered.learners.td3 import TD3, TD3Config
    from layered.learners.td3_group import TD3Group
    from layered.outputs import OutputLayout
    from layered.metrics import Evaluation
    from layered.replay_journal import ReplayJournal
    from layered.runstate import LoopState

    k, capacity = args.seeds, args.rows + args.every * args.checkpoints
    config = TD3Config(buffer_size=capacity, device=args.device)
    space = [Box(-1.0, 1.0, (n,), np.float32) for n in (args.obs, args.act)]
    group = TD3Group([TD3(*space, OutputLayout(args.act), config, seed) for seed in range(k)])
    replay = group.replay
    rng = np.random.default_rng(0)

    def fill(rows: int) -> None:
        """Store `rows` more random transitions per seed, in chunks."""
        for start in range(0, rows, 50_000):
            n = min(50_000, rows - start)
            data = torch.from_numpy(rng.standard_normal((k * n, replay._cuts[-1]), dtype=np.float32))
            replay.restore(replay.stored + n, [(data, replay.stored.copy(), np.full(k, n))])

    fill(args.rows)
    for _ in range(2):  # a critic's and an actor's step: the optimisers' moments exist, as in a trained group
        group.update()
    states = [LoopState() for _ in range(k)]

    def evaluate(seeds: np.ndarray) -> None:
        """An evaluation that is a new best in the `seeds` (a mask): their best weights change."""
        for seed, (state, better) in enumerate(zip(states, seeds, strict=True)):
            score = (state.curve[-1][1].return_mean if state.curve else 0.0) + float(better)
            state.curve.append((len(state.curve), Evaluation(score, 0, 0, 0, 1, 1, 1, {}, {}, {})))
            if better:
                state.best = {"td3": group.seed_state_dict(seed)}

    ways = ("segments, best when changed", "segments, best inline", "whole buffer, best inline")
    seconds: dict[str, list[float]] = {way: [] for way in ways}
    megabytes: dict[str, list[float]] = {way: [] for way in ways}
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as tmp:
        journals = {way: ReplayJournal(Path(tmp) / f"replay-{i}") for i, way in enumerate(ways[:2])}
        best = BestJournal(Path(tmp) / "best")
        evaluate(np.ones(k, bool))  # every seed has best weights, as a group after its first evaluation
        for journal in journals.values():
            journal.record({"td3": replay})  # the rows stored so far, as a group running since the start has them
            journal.prune()
        best.record(range(k), states)
        best.prune()
        for _ in range(args.checkpoints):
            fill(args.every)
            evaluate(rng.random(k) < args.best_share)
            for i, way in enumerate(ways):
                before = _files(Path(tmp))
                start = time.perf_counter()
                state = {"learners": {"td3": group.resume_state()}}
                if way in journals:
                    state["replays"] = journals[way].record({"td3": replay})
                else:
                    state["replay"] = replay.rows_since(np.zeros(k, np.int64))[0]
                if way == ways[0]:
                    state["best"] = best.record(range(k), states)
                else:
                    state["best"] = [s.best for s in states]
                save_checkpoint(Path(tmp) / f"{i}.pt", "group", state, keep_previous=True)
                if way in journals:
                    journals[way].prune()
                if way == ways[0]:
                    best.prune()
                seconds[way].append(time.perf_counter() - start)
                megabytes[way].append(sum(size for name, (stamp, size) in _files(Path(tmp)).items()
                                          if before.get(name, (None,))[0] != stamp) / 1e6)
    print(f"K = {k}, {args.rows} transitions per seed, then {args.every} more before each of {args.checkpoints} "
          f"checkpoints, rows of {replay._cuts[-1]} floats, best weights new in a share {args.best_share} of the "
          f"seeds at each, device {args.device}\n")
    print("| way | seconds per checkpoint | MB written per checkpoint | the group's way faster by |")
    print("|---|---|---|---|")
    for way in ways:
        ratio = np.mean(seconds[way]) / np.mean(seconds[ways[0]])
        print(f"| {way} | {np.mean(seconds[way]):.2f} | {np.mean(megabytes[way]):.0f} | {ratio:.2f}x |")


def _files(folder: Path) -> dict[str, tuple[int, int]]:
    """Each file under `folder` (but a checkpoint's previous copy, renamed, not written) with its time of last
    change and its size: the files a checkpoint wrote are those new or changed since."""
    return {str(p): (p.stat().st_mtime_ns, p.stat().st_size) for p in folder.rglob("*")
            if p.is_file() and ".prev." not in p.name}


if __name__ == "__main__":
    main()
