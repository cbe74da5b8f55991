"""What a group's environment workers cost at its first checkpoint: the time of the first and later snapshots
of their rows, and each worker's private memory before and after (Linux: /proc/PID/smaps_rollup).

    python benchmarks/worker_snapshot.py                       # 2 workers of 4 Hopper-v5 rows each
    python benchmarks/worker_snapshot.py --env Walker2d-v5 --rows 16 --workers 4
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from layered.env_workers import EnvWorkers


def private_mib(pid: int) -> float:
    """The process's private memory (clean and dirty pages it alone maps), in MiB."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:])
    return sum(int(fields[name].split()[0]) for name in ("Private_Clean", "Private_Dirty")) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--rows", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--snapshots", type=int, default=3)
    args = parser.parse_args()
    start = time.perf_counter()
    envs = EnvWorkers(args.env, args.rows, args.workers)
    opened = time.perf_counter() - start
    try:
        every = np.ones(args.rows, bool)
        envs.reset(every, list(range(args.rows)))
        for _ in range(10):
            envs.step_async(np.zeros((args.rows, envs.action_space.shape[0]), np.float32), every, restart=True)
            envs.step_wait()
        pids = [process.pid for process in envs._processes]
        before = [private_mib(pid) for pid in pids]
        times = []
        for _ in range(args.snapshots):
            start = time.perf_counter()
            envs.snapshots()
            times.append(time.perf_counter() - start)
        after = [private_mib(pid) for pid in pids]
    finally:
        envs.close()
    print(f"{args.workers} workers of {args.rows} {args.env} rows: opened in {opened:.2f} s; snapshots "
          + ", ".join(f"{t * 1000:.0f} ms" for t in times)
          + "; private MiB per worker " + ", ".join(f"{b:.0f} -> {a:.0f}" for b, a in zip(before, after, strict=True)))


if __name__ == "__main__":
    main()
