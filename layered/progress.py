"""Progress of a training phase: a live bar on a terminal; elsewhere (a log file, CI, a sweep's
worker) one readable line per evaluation instead of carriage-return bars, with the rate since the
last line and the time the phase has left at that rate."""

from __future__ import annotations

import sys
import time

from tqdm import tqdm



class Progress:
    """Steps of one phase, and each evaluation's return."""

    def __init__(self, label: str, total: int, initial: int, enabled: bool) -> None:
        self.label, self.total = label, total
        self.lines = enabled and not sys.stderr.isatty()
        self.bar = tqdm(total=total, initial=initial, desc=label, unit="step", disable=not enabled or self.lines,
                        dynamic_ncols=True, mininterval=1.0)
        self._since = (time.perf_counter(), initial)

    def advance(self, steps: int) -> None:
        self.bar.update(steps)

    def evaluated(self, step: int, mean: float, std: float) -> None:
        """Show an evaluation's mean return and its spread (over episodes, or over seeds): in the bar's
        postfix, or as one line with the steps per second since the last and the phase's time left."""
        if not self.lines:
            self.bar.set_postfix_str(f"eval return {mean:.1f}")
            return
        now, (then, before) = time.perf_counter(), self._since
        print(f"{self.label}: step {step}/{self.total}, eval return {mean:.1f} ± {std:.1f}"
              f"{pace(step - before, now - then, self.total - step)}", file=sys.stderr, flush=True)
        self._since = (now, step)

    def close(self) -> None:
        self.bar.close()


def pace(steps: int, seconds: float, left: int) -> str:
    """", R steps/s, about T left" for `steps` taken in `seconds` with `left` still to take at that rate
    (nothing for no steps: the phase's first line)."""
    if steps <= 0 or seconds <= 0:
        return ""
    rate = steps / seconds
    return f", {rate:.0f} steps/s" + (f", about {duration(left / rate)} left" if left > 0 else "")


def duration(seconds: float) -> str:
    """A duration as people read it: "40 s", "19 min", "2 h 05 min"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 120 else f"{minutes // 60} h {minutes % 60:02d} min"
