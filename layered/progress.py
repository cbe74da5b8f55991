"""Progress of a training phase: a live bar on a terminal; elsewhere (a log file, CI, a sweep's
worker) one readable line per evaluation instead of carriage-return bars."""

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
        postfix, or as one line with the steps per second since the last."""
        if not self.lines:
            self.bar.set_postfix_str(f"eval return {mean:.1f}")
            return
        now, (then, before) = time.perf_counter(), self._since
        rate = f", {(step - before) / (now - then):.0f} steps/s" if step > before else ""
        print(f"{self.label}: step {step}/{self.total}, eval return {mean:.1f} ± {std:.1f}{rate}", file=sys.stderr,
              flush=True)
        self._since = (now, step)

    def close(self) -> None:
        self.bar.close()
