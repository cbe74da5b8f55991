"""Stopping a run cleanly: SIGINT or SIGTERM asks the loop to checkpoint at the next episode end.

A second signal stops at once (KeyboardInterrupt); the last checkpoint is then the one to resume.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

SIGNAL_NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}


class Stopped(Exception):
    """Training stopped on request after saving a checkpoint; `layered resume` continues it."""

    def __init__(self, signal_name: str, phase: int, step: int, run_dir: Path) -> None:
        self.signal_name, self.phase, self.step, self.run_dir = signal_name, phase, step, run_dir
        super().__init__(f"stopped by {signal_name} in phase {phase} at step {step}, checkpoint saved; "
                         f"continue with: layered resume {run_dir}")


class StopRequest:
    """Set by SIGINT or SIGTERM while installed; the loop reads `requested` where it can checkpoint
    (`until`: a single run's episode end, a group's every step)."""

    def __init__(self, until: str = "this episode") -> None:
        self.requested: str | None = None
        self.until: str | None = until

    def finishing(self) -> None:
        """The last step is behind: a request now lets the run end (its last evaluations and results), as no
        checkpoint could stop it sooner."""
        self.until = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = SIGNAL_NAMES.get(signal.Signals(signum), str(signum))
        doing = (f"finishing {self.until} to save a checkpoint" if self.until is not None else
                 "no step is left: finishing the last evaluations and writing the results")
        print(f"\nlayered: {self.requested}: {doing} (signal again to stop at once)", file=sys.stderr)

    @contextmanager
    def installed(self) -> Iterator[StopRequest]:
        """Handle SIGINT and SIGTERM within the block (only in the main thread, where Python allows it)."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        before = {s: signal.signal(s, self._handle) for s in SIGNAL_NAMES}
        try:
            yield self
        finally:
            for s, handler in before.items():
                signal.signal(s, handler)
