"""The run's CSV logs: rows appended and flushed at once, under a header fixed when the file starts."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any


class CsvLog:
    """A CSV file whose columns are given up front, so no row's values are ever dropped.

    Each row is appended and the file closed at once: its size is then a position a stopped
    run can return to (see `size` and `truncate`).
    """

    def __init__(self, path: Path, fields: Sequence[str]) -> None:
        self.path = path
        self.fields = list(fields)

    def start(self) -> None:
        """Begin the file anew with its header."""
        with self.path.open("w", newline="") as f:
            csv.DictWriter(f, fieldnames=self.fields).writeheader()

    def write(self, row: dict[str, Any]) -> None:
        """Append one row; columns it lacks stay empty, keys outside the header are an error."""
        unknown = set(row) - set(self.fields)
        assert not unknown, f"{self.path.name}: columns {sorted(unknown)} are not in its header"
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.fields, restval="").writerow(row)

    def size(self) -> int:
        """Bytes written so far."""
        return self.path.stat().st_size

    def truncate(self, size: int) -> None:
        """Drop everything after the first `size` bytes (the rows written after a checkpoint)."""
        if not self.path.exists() or self.size() < size:
            raise FileNotFoundError(f"{self.path} is shorter than the {size} bytes its checkpoint recorded")
        with self.path.open("r+b") as f:
            f.truncate(size)
