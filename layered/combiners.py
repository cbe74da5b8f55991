"""Combiners: how a layer's held output joins the action of the layers below it.

The stack walks its layers slowest first, keeping a running sum of contributions. The combiner
of layer i decides what layer i's output does to that walk (`route`) and how the contributions
of the layers below it are admitted (`admit`); the executed action is the sum, clipped once to
the action bounds. Every method works on a leading batch of stacks (`[..., dims]` arrays).

A combiner also describes itself, so that nothing else in the library tests its name: how many
outputs it adds to its layer (`gate_dims`), how a gate output encodes its choice (`encoding`),
whether the layer below acts as a residual (`residual_below`), whether an evaluation threshold
applies (`thresholded`) and how it is written into an exported `stack.json` (`to_json`).

numpy only, with relative imports: the exported runtime carries a copy of this file.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from .outputs import GateEncoding
from .registry import Registry


class Route(enum.IntEnum):
    """What a layer's held output does to the walk down the stack (an array of these per batch)."""

    ADD = 0  # its action joins the sum and the layers below are consulted too
    COMMIT = 1  # its action joins the sum and the layers below are not evaluated
    DEFER = 2  # its action is left out and the layers below act in its place


class Combiner(ABC):
    """How one layer merges with the layers below it; stateless, one instance per level."""

    gate_dims: ClassVar[int] = 0
    """Extra outputs the layer produces beyond the environment's action dimensions."""
    encoding: ClassVar[GateEncoding | None] = None
    """For a combiner that can commit: how its last gate output encodes commit or defer."""
    residual_below: ClassVar[bool] = True
    """Whether the layer below adds to this layer's action (its range is then centred on zero)."""
    thresholded: ClassVar[bool] = False
    """Whether an evaluation threshold applies to the contributions this combiner admits."""

    def __init__(self, threshold: np.ndarray | None = None, per_dimension: bool = False) -> None:
        """`threshold` (absolute, per action dimension) is given at evaluation only."""
        self.threshold = threshold
        self.per_dimension = per_dimension

    @abstractmethod
    def route(self, output: np.ndarray) -> np.ndarray:
        """What the held `output` ([..., action + gate dims]) does to the walk: Route codes of shape [...]."""

    def admit(
        self, above: np.ndarray, contribution: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        """The part of a lower layer's `contribution` that joins the sum `above` (both [..., action
        dims]); the built-in combiners drop parts only at evaluation (they are given a threshold only then)."""
        return contribution

    def to_json(self) -> dict[str, Any]:
        """What `from_json` needs to rebuild this combiner in an exported stack: its registered name
        and settings, as plain JSON values."""
        return {"kind": COMBINERS.name_of(type(self)), "per_dimension": self.per_dimension,
                "threshold": None if self.threshold is None else [float(x) for x in self.threshold]}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Combiner:
        """The combiner `to_json` described."""
        threshold = data["threshold"]
        return cls(None if threshold is None else np.asarray(threshold, np.float32), data["per_dimension"])


COMBINERS: Registry[type[Combiner]] = Registry("combiner", Combiner)


def clip(x: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """`x` within [low, high]: np.clip's result at a third of its call overhead (the rules call it every step)."""
    return np.minimum(np.maximum(x, low), high)


def combiner_from_json(data: dict[str, Any]) -> Combiner:
    """The registered combiner that `Combiner.to_json` described."""
    return COMBINERS.get(data["kind"]).from_json(data)


@COMBINERS.register("residual-clip")
class ResidualClip(Combiner):
    """Lower layers add to this layer's action; the sum is clipped to the bounds (TLA-C).

    At evaluation a lower contribution whose effect on the clipped action is below the
    threshold in every dimension (or, per dimension, in that dimension) is zeroed, so the
    action above it repeats.
    """

    thresholded = True

    def route(self, output: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(output)[:-1], np.int8)  # Route.ADD everywhere

    def admit(
        self, above: np.ndarray, contribution: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        if self.threshold is None:
            return contribution
        effect = np.abs(clip(above + contribution, low, high) - clip(above, low, high))
        small = effect < self.threshold
        if not self.per_dimension:
            small = small.all(axis=-1, keepdims=True)
        return np.where(small, 0.0, contribution).astype(contribution.dtype, copy=False)


@COMBINERS.register("gate")
class Gate(Combiner):
    """The layer outputs an action and a gate; a gate that commits holds its action for its period (TLA-O).

    A committed gate stops the walk, so the layers below are not evaluated; an open gate
    leaves its own action out and defers to the layers below.
    """

    gate_dims = 1
    encoding = GateEncoding(defer=-1.0, commit=1.0)
    residual_below = False

    def route(self, output: np.ndarray) -> np.ndarray:
        commits = self.encoding.commits(np.asarray(output)[..., -1])
        return np.where(commits, Route.COMMIT, Route.DEFER).astype(np.int8)
