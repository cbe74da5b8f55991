"""Combiners: how a layer's held output joins the action of the layers below it.

The stack walks its layers slowest first, keeping a running sum of contributions. The
combiner of layer i decides what layer i's output does to that walk (`route`) and how the
contributions of the layers below it are admitted at evaluation time (`admit`); the executed
action is the sum, clipped once to the action bounds.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from layered.registry import Registry


class Route(enum.Enum):
    """What a layer's held output does to the walk down the stack."""

    ADD = "add"  # its action joins the sum and the layers below are consulted too
    COMMIT = "commit"  # its action joins the sum and the layers below are not evaluated
    DEFER = "defer"  # its action is left out and the layers below act in its place


class Combiner(ABC):
    """How one layer merges with the layers below it; stateless, one instance per level."""

    gate_dims: ClassVar[int] = 0
    """Extra outputs the layer produces beyond the environment's action dimensions."""

    def __init__(self, threshold: np.ndarray | None = None, per_dimension: bool = False) -> None:
        self.threshold = threshold
        self.per_dimension = per_dimension

    @abstractmethod
    def route(self, output: np.ndarray) -> Route:
        """What this layer's held `output` (action plus any gate dims) does to the walk."""

    def admit(
        self, above: np.ndarray, contribution: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        """The part of a lower layer's `contribution` that joins the sum `above`; the built-in
        combiners drop parts only at evaluation (they are given a threshold only then)."""
        return contribution


COMBINERS: Registry[type[Combiner]] = Registry("combiner")


@COMBINERS.register("residual-clip")
class ResidualClip(Combiner):
    """Lower layers add to this layer's action; the sum is clipped to the bounds (TLA-C).

    At evaluation a lower contribution whose effect on the clipped action is below the
    threshold in every dimension (or, per dimension, in that dimension) is zeroed, so the
    action above it repeats.
    """

    def route(self, output: np.ndarray) -> Route:
        return Route.ADD

    def admit(
        self, above: np.ndarray, contribution: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        if self.threshold is None:
            return contribution
        effect = np.abs(np.clip(above + contribution, low, high) - np.clip(above, low, high))
        small = effect < self.threshold
        if self.per_dimension:
            return np.where(small, 0.0, contribution).astype(contribution.dtype)
        return np.zeros_like(contribution) if bool(np.all(small)) else contribution


@COMBINERS.register("gate")
class Gate(Combiner):
    """The layer outputs an action and a gate; gate > 0 commits its action for its period (TLA-O).

    A committed gate stops the walk, so the layers below are not evaluated; an open gate
    leaves its own action out and defers to the layers below.
    """

    gate_dims = 1

    def route(self, output: np.ndarray) -> Route:
        return Route.COMMIT if output[-1] > 0 else Route.DEFER
