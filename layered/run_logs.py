"""A run's logs: metrics.csv (a row per evaluation), episodes.csv (a row per training episode) and, where the
recipe asks, TensorBoard events; opened, started or cut back to a checkpoint, and closed as one, by a single run
and by each seed of a group alike."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from layered.events import EventLog
from layered.logs import CsvLog
from layered.results import EPISODE_FIELDS, metrics_fields
from layered.schema import Recipe


@dataclass
class RunLogs:
    """The logs of the run in one run directory."""

    metrics: CsvLog
    episodes: CsvLog
    events: EventLog | None = None  # TensorBoard scalars, when the recipe asks for them

    @classmethod
    def open(cls, out: Path, recipe: Recipe, resumed_at: tuple[int, int] | None = None) -> RunLogs:
        """The logs in run directory `out` (`resumed_at`: the phase and step a resumed run continues from, where its
        event files go on)."""
        return cls(CsvLog(out / "metrics.csv", metrics_fields(recipe)), CsvLog(out / "episodes.csv", EPISODE_FIELDS),
                   EventLog(out / "tensorboard", resumed_at) if recipe.log.tensorboard else None)

    def begin(self, sizes: dict[str, int] | None = None) -> None:
        """Start the logs afresh, or (`sizes`, as a checkpoint recorded them) cut them back to where it stood."""
        if sizes is None:
            self.metrics.start()
            self.episodes.start()
        else:
            self.metrics.truncate(sizes["metrics"])
            self.episodes.truncate(sizes["episodes"])

    def sizes(self) -> dict[str, int]:
        """How much of each log there is: what a checkpoint records, to cut them back to on resuming."""
        return {"metrics": self.metrics.size(), "episodes": self.episodes.size()}

    def evaluation(self, row: dict[str, Any]) -> None:
        """An evaluation's row, in metrics.csv and the events."""
        self.metrics.write(row)
        if self.events is not None:
            self.events.write(row)

    def close(self) -> None:
        """Close every log (rows written so far are on disk)."""
        self.metrics.close()
        self.episodes.close()
        if self.events is not None:
            self.events.close()
