"""Training orders: which layers learn in each phase and which are present (the rest frozen)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from layered.registry import Registry

if TYPE_CHECKING:
    from layered.schema import Recipe


@dataclass(frozen=True)
class Phase:
    """One training phase: `learn` layers learn, the other `active` layers act frozen."""

    learn: tuple[str, ...]
    active: tuple[str, ...]
    steps: int | None = None  # base steps; None means the recipe's steps_per_phase


Order = Callable[[Sequence[str], Sequence[Any]], list[Phase]]
ORDERS: Registry[Order] = Registry("training order", arguments=2)
MAKE_OWN_PHASES = frozenset({"slow-to-fast", "fast-to-slow", "joint"})
"""The built-in orders that make their own phases: a recipe's `train.phases` would be ignored."""


@ORDERS.register("slow-to-fast")
def slow_to_fast(names: Sequence[str], phases: Sequence[Any] = ()) -> list[Phase]:
    """Closed loop (TLA-C): train the slowest alone, freeze it, train the next on top, and so on."""
    return [Phase(learn=(name,), active=tuple(names[: k + 1])) for k, name in enumerate(names)]


@ORDERS.register("fast-to-slow")
def fast_to_slow(names: Sequence[str], phases: Sequence[Any] = ()) -> list[Phase]:
    """Open loop (TLA-O): train the fastest alone, then each slower layer on top of the trained ones."""
    n = len(names)
    return [Phase(learn=(names[k],), active=tuple(names[k:])) for k in range(n - 1, -1, -1)]


@ORDERS.register("joint")
def joint(names: Sequence[str], phases: Sequence[Any] = ()) -> list[Phase]:
    """Every layer learns at once in one phase (the authors' jointly trained gated TLA)."""
    return [Phase(learn=tuple(names), active=tuple(names))]


@ORDERS.register("explicit")
def explicit(names: Sequence[str], phases: Sequence[Any] = ()) -> list[Phase]:
    """The recipe's own phases; a phase's active layers default to its learners plus all trained before."""
    trained: set[str] = set()
    out = []
    for phase in phases:
        wanted = set(phase.active) if phase.active is not None else set(phase.learn) | trained
        wanted |= set(phase.learn)
        out.append(Phase(learn=tuple(phase.learn), active=tuple(n for n in names if n in wanted), steps=phase.steps))
        trained |= set(phase.learn)
    return out


def phases_of(recipe: Recipe) -> list[Phase]:
    """The phases of the recipe's training order."""
    return ORDERS.get(recipe.train.order)(recipe.layer_names(), recipe.train.phases or [])


def stack_weights(recipe: Recipe, weights: str | None = None, phase: int = -1) -> dict[str, str]:
    """Which saved weights, `final` or `best`, make each layer of the stack that phase `phase` (by default the
    run's last) ends with: `weights` (default: `train.select`) for the layers that learn in that phase, and for
    every other layer what its own last phase handed on (`train.select`), the weights the phase trained over and
    was evaluated with."""
    learn = phases_of(recipe)[phase].learn
    return {name: (weights or recipe.train.select) if name in learn else recipe.train.select
            for name in recipe.layer_names()}
