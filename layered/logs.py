"""The run's CSV logs: rows appended and flushed at once, under a header fixed when the file starts."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from layered.errors import BadInput


class CsvLog:
    """A CSV file whose columns are given up front, so no row's values are ever dropped.

    Each row is appended and flushed at once: the file's size is then a position a stopped run can return
    to (see `size` and `truncate`). The file stays open between rows (opening and closing it for each made
    a row about four times as costly, and a group of many seeds logs a row per episode end); `close` when
    done.
    """

    def __init__(self, path: Path, fields: Sequence[str]) -> None:
        self.path = path
        self.fields = list(fields)
        self._columns = frozenset(self.fields)
        self._file: IO[str] | None = None
        self._writer: csv.DictWriter[str] | None = None

    def start(self) -> None:
        """Begin the file anew with its header."""
        self._open("w").writeheader()
        self._flush()

    def write(self, row: dict[str, Any]) -> None:
        """Append one row; columns it lacks stay empty, keys outside the columns given are an error (those given
        but not in the header of a file begun by an earlier version, see `truncate`, are left out)."""
        unknown = row.keys() - self._columns
        assert not unknown, f"{self.path.name}: columns {sorted(unknown)} are not in its header"
        (self._writer or self._open("a")).writerow(row)
        self._flush()

    def size(self) -> int:
        """Bytes written so far."""
        return self.path.stat().st_size

    def truncate(self, size: int) -> None:
        """Drop everything after the first `size` bytes (the rows written after a checkpoint), and go on under the
        file's own header: one begun before a column was added (by an earlier version of layered) gets its rows
        without that column, in the places its header gives, not shifted by it."""
        self.close()
        if not self.path.exists() or self.size() < size:
            state = f"shorter than the {size} bytes its checkpoint recorded" if self.path.exists() else "missing"
            raise BadInput(f"{self.path} is {state}: the rows the run wrote before that checkpoint are lost, so it "
                           "cannot continue exactly; train it again with --force")
        with self.path.open("r+b") as f:
            f.truncate(size)
        with self.path.open(newline="") as f:
            header = next(csv.reader(f), [])
        unknown = [column for column in header if column not in self._columns]
        if unknown:
            raise BadInput(f"{self.path}: its columns {unknown} are not among those this run writes")
        self.fields = header

    def close(self) -> None:
        """Close the file (a later row opens it again)."""
        if self._file is not None:
            self._file.close()
        self._file = self._writer = None

    def _open(self, mode: str) -> csv.DictWriter[str]:
        self.close()
        self._file = self.path.open(mode, newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=self.fields, restval="", extrasaction="ignore")
        return self._writer

    def _flush(self) -> None:
        assert self._file is not None
        self._file.flush()
