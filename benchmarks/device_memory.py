"""The GPU memory of the processes a measured command starts, as the driver reports it per process (each
process's CUDA context included, which torch's own counters leave out): polled with `nvidia-smi` while the
command runs, the largest value seen per process kept. Where there is no `nvidia-smi` (a CPU), nothing is
measured and the figures are None.

    with DeviceMemory() as memory:
        subprocess.run([...])
    memory.largest(), memory.total()   # MiB: the largest process's peak, and the sum of the processes' peaks
"""

from __future__ import annotations

import subprocess
import threading
from types import TracebackType

QUERY = ["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"]


def parse(text: str) -> dict[int, float]:
    """`nvidia-smi`'s lines `pid, MiB` as {pid: MiB}; lines it cannot tell a value for ("[N/A]") are left out."""
    used: dict[int, float] = {}
    for line in text.splitlines():
        pid, _, mib = (part.strip() for part in line.partition(","))
        if pid.isdigit() and mib.replace(".", "", 1).isdigit():
            used[int(pid)] = float(mib)
    return used


class DeviceMemory:
    """Each process's peak GPU memory (MiB) while the block runs, leaving out processes already there before it."""

    def __init__(self, every: float = 0.5) -> None:
        self.every = every
        self.peaks: dict[int, float] = {}
        self.available = True
        self._before: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def __enter__(self) -> DeviceMemory:
        self._before = set(self._read() or {})
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def largest(self) -> float | None:
        """The largest peak of one process (a sweep's heaviest run), or None where nothing was measured."""
        return max(self.peaks.values()) if self.peaks else None

    def total(self) -> float | None:
        """The processes' peaks summed (a group's process, or a sweep's all), or None where nothing was measured."""
        return sum(self.peaks.values()) if self.peaks else None

    def _poll(self) -> None:
        while not self._stop.wait(self.every):
            for pid, mib in (self._read() or {}).items():
                if pid not in self._before:
                    self.peaks[pid] = max(mib, self.peaks.get(pid, 0.0))

    def _read(self) -> dict[int, float] | None:
        """The processes' memory now; None (and no more polling) where `nvidia-smi` is missing or fails."""
        try:
            out = subprocess.run(QUERY, capture_output=True, text=True, timeout=10, check=True).stdout
        except (OSError, subprocess.SubprocessError):
            self.available = False
            self._stop.set()
            return None
        return parse(out)


def mib(value: float | None, per: int = 1) -> str:
    """`value` MiB shared by `per` seeds, for a table cell ("n/a" where nothing was measured)."""
    return "n/a" if value is None else f"{value / per:,.0f}"
