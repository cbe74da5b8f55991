"""The progress line of a phase run without a terminal: its rate and time left, computed by hand."""

from __future__ import annotations

import pytest

from layered import progress
from layered.progress import Progress, duration, pace


@pytest.mark.parametrize(("seconds", "text"), [(0.4, "0 s"), (40, "40 s"), (89, "89 s"), (90, "2 min"),
                                               (19 * 60 + 20, "19 min"), (119 * 60 + 29, "119 min"),
                                               (125 * 60, "2 h 05 min"), (26 * 3600, "26 h 00 min")])
def test_durations_read_as_people_write_them(seconds, text):
    assert duration(seconds) == text


def test_the_pace_is_the_rate_since_the_last_line_and_the_time_left_at_it():
    # 5000 steps in 80 s: 62.5 steps/s; 70 000 left at that rate: 1120 s, 18.7 min
    assert pace(5000, 80.0, 70_000) == ", 62 steps/s, about 19 min left"
    assert pace(5000, 80.0, 0) == ", 62 steps/s"  # the phase's last line
    assert pace(5000, 80.0, -2) == ", 62 steps/s"  # a phase that ran past its budget to end a slow layer's period
    assert pace(5000, 80.0, None) == ", 62 steps/s"  # no estimate asked for
    assert pace(0, 0.0, 100_000) == ""  # its first
    # a group of 10 seeds, each taking the 5000 steps: 62.5 per seed, 625 in all; the time left is the seeds'
    assert pace(5000, 80.0, 70_000, seeds=10) == ", 62 steps/s per seed (625 in all), about 19 min left"
    assert pace(5000, 80.0, 70_000, later=1) == ", 62 steps/s, about 19 min left in this phase, then 1 more phase"
    assert pace(5000, 80.0, 70_000, later=2).endswith("left in this phase, then 2 more phases")


def test_a_phase_without_a_terminal_prints_one_line_per_evaluation(capsys, monkeypatch):
    """A phase resumed at step 10 000 of 100 000: two warm-up intervals (no update), the one where updates
    begin, and two that update throughout; only those two estimate the time left."""
    clock = iter([0.0, 10.0, 20.0, 100.0, 180.0, 200.0])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    bar = Progress("phase 0: slow (10 seeds)", total=100_000, initial=10_000, enabled=True, seeds=10)
    bar.evaluated(10_000, -1.0, 0.0, learned=False)  # the phase's first line (no interval yet)
    bar.evaluated(15_000, 2.0, 1.0, learned=False)
    bar.evaluated(25_000, 151.84, 18.76, learned=True)
    bar.evaluated(30_000, 160.0, 20.0, learned=True)
    bar.evaluated(35_000, 170.0, 20.0, learned=True)
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    head = "phase 0: slow (10 seeds): step "
    group = "steps/s per seed"
    assert lines == [f"{head}10000/100000, eval return -1.0 ± 0.0",
                     f"{head}15000/100000, eval return 2.0 ± 1.0, 500 {group} (5000 in all), warm-up",  # 5000 in 10 s
                     # 10 000 in 80 s, partly warm-up
                     f"{head}25000/100000, eval return 151.8 ± 18.8, 125 {group} (1250 in all)",
                     # 5000 in 80 s: 62.5 steps/s; 70 000 left: 1120 s
                     f"{head}30000/100000, eval return 160.0 ± 20.0, 62 {group} (625 in all), about 19 min left",
                     # 5000 in 20 s: 250 steps/s; 65 000 left: 260 s
                     f"{head}35000/100000, eval return 170.0 ± 20.0, 250 {group} (2500 in all), about 4 min left"]
