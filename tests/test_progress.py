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
    assert pace(0, 0.0, 100_000) == ""  # its first


def test_a_phase_without_a_terminal_prints_one_line_per_evaluation(capsys, monkeypatch):
    clock = iter([100.0, 180.0, 200.0])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    bar = Progress("phase 0: slow (10 seeds)", total=100_000, initial=25_000, enabled=True)
    bar.evaluated(30_000, 151.84, 18.76)
    bar.evaluated(35_000, 160.0, 20.0)
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["phase 0: slow (10 seeds): step 30000/100000, eval return 151.8 ± 18.8, 62 steps/s, "
                     "about 19 min left",
                     "phase 0: slow (10 seeds): step 35000/100000, eval return 160.0 ± 20.0, 250 steps/s, "
                     "about 4 min left"]  # 65 000 steps at 250 steps/s: 260 s
