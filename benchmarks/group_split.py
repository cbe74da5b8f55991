"""K seeds cut into S groups trained at once, each on its share of this process's cores: the one cut the
benchmarks that measure several groups side by side make (`gpu.py --splits`, `group_vs_sweep.py --splits`)."""

from __future__ import annotations

import os


def groups_at_once(seeds: int, splits: int) -> list[tuple[range, list[int]]]:
    """Each group's seeds (contiguous, as even as can be) and cores (this process's, shared out the same way; one
    each, shared, where there are more groups than cores)."""
    cores = sorted(os.sched_getaffinity(0))
    return [(range(seeds * j // splits, seeds * (j + 1) // splits),
             cores[len(cores) * j // splits: len(cores) * (j + 1) // splits] or [cores[j % len(cores)]])
            for j in range(splits)]
