"""An exported stack's time per `step` back to back (what `layered export` prints) against the same steps at a
control rate, with the processor idle between them (its caches cold), alternately, on one torch thread.

    layered export RUN                                  # writes RUN/export-torchscript
    python benchmarks/exported_step_rate.py RUN/export-torchscript --pause 0.05 --repeats 3

Prints, per repeat, the median microseconds of `--steps` steps on observations drawn uniformly from [-1, 1].
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("export", type=Path, help="an exported stack's folder")
    parser.add_argument("--pause", type=float, default=0.05, help="seconds between steps at the control rate")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    sys.path.insert(0, str(args.export))
    from layered_runtime import load_stack

    stack = load_stack(args.export)
    size = json.loads((args.export / "stack.json").read_text())["env_observation_dims"]
    observations = np.random.default_rng(0).uniform(-1, 1, (args.steps, size)).astype(np.float32)

    def median_us(pause: float) -> float:
        stack.reset()
        times = []
        for obs in observations:
            start = time.perf_counter()
            stack.step(obs)
            times.append(time.perf_counter() - start)
            if pause:
                time.sleep(pause)
        return statistics.median(times) * 1e6

    for repeat in range(args.repeats):
        print(f"repeat {repeat}: back to back {median_us(0.0):.0f} µs, "
              f"{args.pause * 1e3:g} ms between steps {median_us(args.pause):.0f} µs")


if __name__ == "__main__":
    main()
