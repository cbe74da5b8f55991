"""The GPU benchmark reads a run's rate from the progress lines `layered` writes (benchmarks/gpu.py's
`settled_rate`): lines made here by `layered.progress`, for a single run and for a group, read by hand."""

import sys
from itertools import accumulate
from pathlib import Path

import pytest

from layered import progress
from layered.progress import Progress

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from gpu import Failed, settled_rate


def lines(capsys, monkeypatch, label, seeds, later, seconds, learned):
    """The progress lines of one phase of 50 000 steps, an evaluation every 5000, the intervals taking `seconds`
    and updating or not as `learned` says."""
    clock = iter(accumulate([0.0, 0.0, *seconds]))  # (the bar reads the clock when made, and at each evaluation)
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    bar = Progress(label, total=50_000, initial=0, enabled=True, seeds=seeds, later=later)
    for k, did in enumerate([False, *learned]):
        bar.evaluated(5000 * k, 0.0, 1.0, learned=did)
    bar.close()
    return capsys.readouterr().err


@pytest.mark.parametrize(("seeds", "later"), [(1, 0), (1, 1), (32, 0), (32, 1)])
def test_the_settled_rate_is_the_median_of_the_updating_intervals_after_the_first(capsys, monkeypatch, seeds, later):
    # intervals of 5000 steps: two of warm-up (10 s: 500 steps/s), the first with updates (40 s: 125), then three
    # at 50 s, 20 s and 25 s: 100, 250 and 200 steps/s per seed. The rate: the median of the last three, 200.
    log = lines(capsys, monkeypatch, f"phase 0: td3{f' ({seeds} seeds)' if seeds > 1 else ''}", seeds, later,
                [10.0, 10.0, 40.0, 50.0, 20.0, 25.0], [False, False, True, True, True, True])
    assert ("per seed (6400 in all)" in log) == (seeds > 1) and ("then 1 more phase" in log) == (later == 1)
    assert settled_rate(log) == 200


def test_a_log_without_an_updating_interval_after_the_first_is_a_failure_that_says_so(capsys, monkeypatch):
    log = lines(capsys, monkeypatch, "phase 0: td3 (4 seeds)", 4, 0, [10.0, 40.0], [False, True])
    with pytest.raises(Failed, match="too few progress lines"):
        settled_rate(log)
