"""TensorBoard event files beside the CSV logs (`log.tensorboard`): every row of metrics.csv again as
scalars, one TensorBoard run per phase (so phases overlay on one chart), against environment steps
in the phase. metrics.csv stays the source of truth; these are written from its rows."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

EVAL_TAGS = {
    "return_mean": "eval/return", "return_std": "eval/return_std", "return_min": "eval/return_min",
    "return_max": "eval/return_max", "repetition": "eval/action_repetition",
    "repetition_at_bounds": "eval/action_repetition_at_bounds",
    "repetition_held": "eval/action_repetition_held",
    "jerk": "eval/jerk", "decisions": "eval/decisions", "compute": "eval/compute_macs",
    "episode_steps": "eval/episode_steps",
}
LAYER_TAG = re.compile(r"^(decided|acted|contribution|critic_loss|actor_loss)_(.+)$")


def tag(key: str) -> str | None:
    """The scalar tag of a metrics.csv column: `eval/...`, `layer/<name>/...` or `loss/<name>/...`."""
    if key in EVAL_TAGS:
        return EVAL_TAGS[key]
    match = LAYER_TAG.match(key)
    if match is None:
        return None
    what, layer = match.groups()
    if what.endswith("_loss"):
        return f"loss/{layer}/{what.removesuffix('_loss')}"
    return f"layer/{layer}/{what}"


def available() -> bool:
    """Whether the optional `tensorboard` package (the extra layered-control[tensorboard]) is installed."""
    import importlib.util

    return importlib.util.find_spec("tensorboard") is not None


class EventLog:
    """Writes metrics rows as TensorBoard scalars under `root/phase-<p>-<learning layers>/`."""

    def __init__(self, root: Path, resumed_at: tuple[int, int] | None = None) -> None:
        """`resumed_at` (phase, step): a resumed run drops the events written after the checkpoint it
        resumes from: that phase's after that step, and any of later phases."""
        self.root = root
        self.resumed_at = resumed_at
        self.writers: dict[int, Any] = {}

    def write(self, row: dict[str, Any]) -> None:
        writer = self._writer(int(row["phase"]), str(row["learn"]))
        for key, value in row.items():
            name = tag(key)
            if name is not None and isinstance(value, int | float) and math.isfinite(value):
                writer.add_scalar(name, value, int(row["step"]))
        writer.flush()

    def _writer(self, phase: int, learn: str) -> Any:
        if phase not in self.writers:
            from torch.utils.tensorboard import SummaryWriter

            purge = None
            if self.resumed_at is not None and phase >= self.resumed_at[0]:
                purge = self.resumed_at[1] + 1 if phase == self.resumed_at[0] else 0  # its row at that step stays
            self.writers[phase] = SummaryWriter(str(self.root / f"phase-{phase}-{learn}"), purge_step=purge)
        return self.writers[phase]

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
