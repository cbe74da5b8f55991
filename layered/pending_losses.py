"""The losses of a layer's updates, kept on the learner's device until the loop reads them back (at an
evaluation or a checkpoint) in one copy, rather than one host round-trip per update.

They are copied into one buffer on the device that grows by doubling, not kept as one small tensor per
update: on a CPU, thousands of small allocations that live on between updates settle in the holes the
updates' large temporaries leave in glibc's heap, which then can no longer take the next update's
temporaries and grows instead. A float32 group of 8 Pendulum seeds kept about 1.7 MB per update so,
2.1 GB at 1000 updates, where the buffer keeps it at its size without them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch


class PendingLosses:
    """Each update's named losses (tensors of one shape on one device), with a note of the caller's per update."""

    def __init__(self) -> None:
        self._buffer: torch.Tensor | None = None
        self._rows = 0
        self._updates: list[tuple[tuple[str, ...], Any]] = []

    def __len__(self) -> int:
        """The updates kept."""
        return len(self._updates)

    def add(self, losses: Mapping[str, torch.Tensor], note: Any = None) -> None:
        """Keep one update's `losses` (copied into the buffer; no host round-trip) and `note` with them."""
        for value in losses.values():
            self._room(value)
            assert self._buffer is not None
            self._buffer[self._rows].copy_(value)
            self._rows += 1
        self._updates.append((tuple(losses), note))

    def read(self) -> list[tuple[dict[str, Any], Any]]:
        """Every update kept, in order, as (its losses on the host by name, its note), read off the device in
        one copy; the buffer is then empty (and keeps its size)."""
        values = iter(np.empty(0) if self._buffer is None else self._buffer[: self._rows].cpu().numpy())
        updates = [({name: next(values) for name in names}, note) for names, note in self._updates]
        self._rows, self._updates = 0, []
        return updates

    def _room(self, value: torch.Tensor) -> None:
        """A buffer with a free row for `value`, twice as large as before if it was full."""
        buffer = self._buffer
        if buffer is None or buffer.shape[1:] != value.shape or buffer.device != value.device:
            assert self._rows == 0, "one shape and one device for all the losses kept"
            self._buffer = torch.empty((64, *value.shape), dtype=torch.float32, device=value.device)
        elif self._rows == len(buffer):
            self._buffer = torch.cat([buffer, torch.empty_like(buffer)])
