"""Progress of a training phase: a live bar on a terminal; elsewhere (a log file, CI, a sweep's
worker) one readable line per evaluation instead of carriage-return bars, with the rate since the
last line and, once the phase's updates run, the time it has left at that rate."""

from __future__ import annotations

import sys
import time

from tqdm import tqdm


class Progress:
    """Steps of one phase, and each evaluation's return. `seeds`: how many seeds take each step together
    (a group's); its lines give the rate per seed and in all. `later`: the run's phases after this one, whose
    time its estimate leaves out (they run at rates of their own)."""

    def __init__(self, label: str, total: int, initial: int, enabled: bool, seeds: int = 1, later: int = 0) -> None:
        self.label, self.total, self.seeds, self.later = label, total, seeds, later
        self.lines = enabled and not sys.stderr.isatty()
        self.bar = tqdm(total=total, initial=initial, desc=label, unit="step", disable=not enabled or self.lines,
                        dynamic_ncols=True, mininterval=1.0)
        self._since = (time.perf_counter(), initial)
        self._learned = False  # whether the layers updated in the interval that ended at the last line

    def advance(self, steps: int) -> None:
        """Move the bar on by `steps` environment steps."""
        self.bar.update(steps)

    def evaluated(self, step: int, mean: float, std: float, learned: bool) -> None:
        """Show an evaluation's mean return and its spread (over episodes, or over seeds): in the bar's
        postfix, or as one line with the steps per second since the last. `learned`: whether the phase's
        layers updated since the last line; a warm-up interval (none did) is said so, and the time left is
        estimated only from an interval that updated throughout (one after another that updated), since
        warm-up steps are many times faster."""
        if not self.lines:
            self.bar.set_postfix_str(f"eval return {mean:.1f}")
            return
        now, (then, before) = time.perf_counter(), self._since
        left = self.total - step if learned and self._learned else None
        print(f"{self.label}: step {step}/{self.total}, eval return {mean:.1f} ± {std:.1f}"
              f"{pace(step - before, now - then, left, self.seeds, self.later)}"
              f"{'' if learned or step == before else ', warm-up'}",
              file=sys.stderr, flush=True)
        self._since, self._learned = (now, step), learned

    def close(self) -> None:
        self.bar.close()


def pace(steps: int, seconds: float, left: int | None, seeds: int = 1, later: int = 0) -> str:
    """", R steps/s" for `steps` taken in `seconds` (by each of `seeds` seeds: ", R steps/s per seed (R x seeds
    in all)"), and ", about T left" for `left` more steps at that rate (nothing for no steps: a phase's first
    line; no time left for `left` None, 0 or below, a phase past its budget by a period's last steps), "in this
    phase, then N more" where `later` phases follow."""
    if steps <= 0 or seconds <= 0:
        return ""
    rate = steps / seconds
    each = f"{rate:.0f} steps/s" + (f" per seed ({rate * seeds:.0f} in all)" if seeds > 1 else "")
    after = f" in this phase, then {count(later, 'more phase')}" if later else ""
    return f", {each}" + (f", about {duration(left / rate)} left{after}" if left and left > 0 else "")


def count(n: int, noun: str) -> str:
    """`1 seed`, `3 seeds`."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def duration(seconds: float) -> str:
    """A duration as people read it: "40 s", "19 min", "2 h 05 min"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 120 else f"{minutes // 60} h {minutes % 60:02d} min"
