"""The layout of a layer's output vector: its action, then any gate outputs, then any repeat count."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OutputLayout:
    """What each entry of a layer's output means; learners are given this instead of guessing it."""

    action_dims: int
    """Entries that act on the environment (residual or absolute, as the combiner above says)."""
    gate_dims: int = 0
    """Entries after the action that the layer's combiner reads as gates (commit when > 0)."""
    max_repeat: int = 1
    """Above 1 the last entry is a repeat count in 1..max_repeat (periods to hold the output)."""

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
