"""The losses of a layer's updates, kept on the learner's device until the loop reads them back (at an
evaluation or a checkpoint) in one copy, rather than one host round-trip per update.

They are copied into one buffer on the device that grows by doubling, not kept as one small tensor per
update: on a CPU, thousands of small allocations that live on between updates settle in the holes the
updates' large temporaries leave in glibc's heap, which then can no longer take the next update's
temporaries and grows instead: by about 1.7 MB per update for a float32 group of 8 Pendulum seeds,
which peaked at 2.49 GB after 1000 updates, and at 0.58 GB with the buffer.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

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
            buffer = self._room(value)
            assert buffer.shape[1:] == value.shape, "one shape for all the losses kept"
            buffer[self._rows].copy_(value)
            self._rows += 1
        self._updates.append((tuple(losses), note))

    def read(self) -> list[tuple[dict[str, Any], Any]]:
        """Every update kept, in order, as (its losses on the host by name, its note), read off the device in
        one copy; the buffer is then empty (and keeps its size)."""
        if self._buffer is None or not self._updates:
            return []
        values = iter(self._buffer[: self._rows].cpu().numpy())
        updates = [({name: next(values) for name in names}, note) for names, note in self._updates]
        self._rows, self._updates = 0, []
        return updates

    def _room(self, value: torch.Tensor) -> torch.Tensor:
        """The buffer, with a free row for `value` (made for its shape and device, or made twice as large)."""
        if self._buffer is None:
            self._buffer = torch.empty((64, *value.shape), dtype=torch.float32, device=value.device)
        elif self._rows == len(self._buffer):
            self._buffer = torch.cat([self._buffer, torch.empty_like(self._buffer)])
        return self._buffer
