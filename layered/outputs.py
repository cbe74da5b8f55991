"""The layout of a layer's output vector: its action, then any gate outputs, then any repeat count.

Pure Python, no dependencies: the exported runtime carries a copy of this file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class GateEncoding:
    """How a gate output encodes its choice: `commit` and `defer` are the values a learner writes, and
    a value above their midpoint commits."""

    defer: float = -1.0
    commit: float = 1.0

    def commits(self, value: Any) -> Any:
        """Whether gate output(s) `value` commit (a bool, or a bool array for an array)."""
        return value > (self.defer + self.commit) / 2

    def value(self, commit: bool) -> float:
        """The gate output that makes this choice."""
        return self.commit if commit else self.defer


@dataclass(frozen=True)
class OutputLayout:
    """What each entry of a layer's output means; learners are given this instead of guessing it."""

    action_dims: int
    """Entries that act on the environment (residual or absolute, as the combiner above says)."""
    gate_dims: int = 0
    """Entries after the action that the layer's combiner reads as gates."""
    max_repeat: int = 1
    """Above 1 the last entry is a repeat count in 1..max_repeat (periods to hold the output)."""
    gate: GateEncoding | None = None
    """How the last gate entry encodes commit or defer, where the layer's combiner is a gate."""

    @property
    def repeats(self) -> bool:
        """Whether the output ends with a repeat count."""
        return self.max_repeat > 1

    @property
    def size(self) -> int:
        """Length of the whole output vector."""
        return self.action_dims + self.gate_dims + int(self.repeats)

    def describe(self) -> str:
        """A short phrase for error messages, e.g. `1 action + 1 gate`."""
        parts = [f"{self.action_dims} action"]
        if self.gate_dims:
            parts.append(f"{self.gate_dims} gate")
        if self.repeats:
            parts.append(f"a repeat count up to {self.max_repeat}")
        return " + ".join(parts)
