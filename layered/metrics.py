"""The paper's measures of a controller, from the base steps of evaluation episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


Bounds = tuple[np.ndarray, np.ndarray]  # the environment's action space: low and high


@dataclass(frozen=True)
class StepRecord:
    """One base step as executed: the action, which layers decided, what each contributed, and the
    observation it was executed from."""

    action: np.ndarray
    reward: float
    decided: tuple[str, ...]  # layers whose network was evaluated at this step
    contributions: dict[str, np.ndarray]  # per layer the walk reached: its part of the action
    obs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    def size(self, name: str) -> float:
        """Mean |contribution| of layer `name` over action dimensions (0 where the walk did not reach it)."""
        part = self.contributions.get(name)
        return 0.0 if part is None else float(np.mean(np.abs(part)))

    @property
    def acted(self) -> tuple[str, ...]:
        """Layers whose contribution to the action was non-zero."""
        return tuple(name for name in self.contributions if self.size(name) > 0)


def normalised_auc(steps: Sequence[float], returns: Sequence[float], return_range: tuple[float, float]) -> float:
    """Trapezoidal area under the evaluation curve, returns mapped to [0, 1] by (worst, best),
    divided by the training span; a single evaluation gives its normalised return."""
    worst, best = return_range
    y = (np.asarray(returns, np.float64) - worst) / (best - worst)
    x = np.asarray(steps, np.float64)
    if len(x) < 2 or x[-1] == x[0]:
        return float(y[-1])
    return float(np.trapezoid(y, x) / (x[-1] - x[0]))


def at_bounds(actions: np.ndarray, bounds: Bounds) -> np.ndarray:
    """Whether each action (the last axis its dimensions) lies at a bound of the environment's action space in every
    dimension: an actor held at its limits (a saturated one), whose repeats are not decisions held."""
    low, high = bounds
    return np.all((actions <= low) | (actions >= high), axis=-1)


def held(decided: np.ndarray, acted: np.ndarray, reached: np.ndarray, acted_before: np.ndarray,
         reached_before: np.ndarray) -> np.ndarray:
    """Whether the stack's rules repeated each step's action (arrays [..., layers], the step's and, `_before`, the
    previous step's): every layer either had a part in neither action (its part zero: thresholded away, deferring,
    or kept out by a committed gate), or decided nothing anew and was reached by the walk at both steps or at
    neither. Then every part is the one before, and so is their sum: the outputs of layers that decided anew count
    only through their parts being zero."""
    quiet = ~acted & ~acted_before
    kept = ~decided & (reached == reached_before)
    return np.all(quiet | kept, axis=-1)


def best_evaluation(returns: Sequence[float]) -> int:
    """Index of a phase's best evaluation among its mean `returns`: the highest, the earliest on ties (the
    evaluation whose weights a run keeps as its best)."""
    return list(returns).index(max(returns))


@dataclass(frozen=True)
class EpisodeMeasures:
    """One episode's return, length, action repetition (all of it, that at the action bounds and that the stack's
    rules held), jerk, decisions, compute and per-layer activity."""

    ret: float
    steps: int
    repetition: float
    repetition_at_bounds: float
    repetition_held: float
    jerk: float
    decisions: int  # steps at which any layer's network was evaluated
    compute: int  # multiply-accumulates of every network evaluation
    decided: dict[str, int] = field(default_factory=dict)  # per layer: steps it was evaluated
    acted: dict[str, int] = field(default_factory=dict)  # per layer: steps its contribution was non-zero
    contribution: dict[str, float] = field(default_factory=dict)  # per layer: sum over steps of mean |c|


def measure_episode(trace: Sequence[StepRecord], macs: dict[str, int], bounds: Bounds) -> EpisodeMeasures:
    """Measures of one episode from its steps; `macs` is each layer's cost of one decision, `bounds` the
    environment's action bounds. The sums an `EpisodeMeter` keeps step by step, taken over the whole episode at
    once, in the order it adds them."""
    names, steps = list(macs), len(trace)
    actions = np.array([s.action for s in trace], np.float64).reshape(steps, -1) if trace else np.zeros((0, 0))
    decided = np.array([[n in s.decided for n in names] for s in trace], bool).reshape(steps, len(names))
    reached = np.array([[n in s.contributions for n in names] for s in trace], bool).reshape(steps, len(names))
    sizes = np.array([[s.size(n) for n in names] for s in trace], np.float64).reshape(steps, len(names))
    repeats = np.all(actions[1:] == actions[:-1], axis=1)
    acted = sizes > 0
    return _measures(
        names, ret=_in_order(np.array([s.reward for s in trace], np.float64)), steps=steps,
        repeats=int(repeats.sum()), bound_repeats=int((repeats & at_bounds(actions[1:], bounds)).sum()),
        held_repeats=int(held(decided[1:], acted[1:], reached[1:], acted[:-1], reached[:-1]).sum()),
        change=_in_order(np.abs(actions[1:] - actions[:-1]).sum(axis=1)), dims=actions.shape[1],
        decisions=int(decided.any(axis=1).sum()), compute=int((decided.astype(np.int64) @ _costs(names, macs)).sum()),
        decided=decided.sum(axis=0), acted=acted.sum(axis=0), contribution=_in_order(sizes))


def _in_order(values: np.ndarray) -> Any:
    """The sum over the first axis, added one after another (as a meter adds a step at a time; numpy's own sum
    adds pairwise, which rounds otherwise)."""
    return np.add.accumulate(values, axis=0)[-1] if len(values) else np.zeros(values.shape[1:])


def _costs(layers: Sequence[str], macs: dict[str, int]) -> np.ndarray:
    return np.array([macs[n] for n in layers], np.int64)


def _measures(layers: Sequence[str], ret: float, steps: int, repeats: int, bound_repeats: int, held_repeats: int,
              change: float, dims: int, decisions: int, compute: int, decided: np.ndarray, acted: np.ndarray,
              contribution: np.ndarray) -> EpisodeMeasures:
    """An episode's measures from its sums: of rewards, of steps whose action repeats the previous one (of those
    whose repeated action is at the action bounds, and of the steps whose action the rules held: `held`), of the
    actions' absolute changes over steps and `dims` dimensions, and per layer of decisions, steps acted and mean
    |contribution|."""
    return EpisodeMeasures(
        ret=float(ret), steps=steps, repetition=float(repeats / steps) if steps else 0.0,
        repetition_at_bounds=float(bound_repeats / steps) if steps else 0.0,
        repetition_held=float(held_repeats / steps) if steps else 0.0,
        jerk=float(change / ((steps - 1) * dims)) if steps > 1 else 0.0, decisions=int(decisions), compute=int(compute),
        decided={n: int(v) for n, v in zip(layers, decided, strict=True)},
        acted={n: int(v) for n, v in zip(layers, acted, strict=True)},
        contribution={n: float(v) for n, v in zip(layers, contribution, strict=True)})


class EpisodeMeter:
    """The measures of `rows` episodes under way at once (a group evaluation's rows), their sums kept step by
    step in arrays: a batch of episodes is measured without a loop over its rows."""

    def __init__(self, rows: int, layers: Sequence[str], macs: dict[str, int], bounds: Bounds) -> None:
        """`macs`: each layer's cost of one decision; `bounds`: the environment's action bounds."""
        self.layers = list(layers)
        self.macs = _costs(self.layers, macs)
        self.bounds = bounds
        width = len(self.layers)
        self.ret, self.steps = np.zeros(rows), np.zeros(rows, np.int64)
        self.repeats, self.bound_repeats = np.zeros(rows, np.int64), np.zeros(rows, np.int64)
        self.held_repeats = np.zeros(rows, np.int64)
        self.change = np.zeros(rows)  # |a_t - a_t-1| summed over dimensions
        self.decisions, self.compute = np.zeros(rows, np.int64), np.zeros(rows, np.int64)
        self.decided, self.acted = np.zeros((rows, width), np.int64), np.zeros((rows, width), np.int64)
        self.contribution = np.zeros((rows, width))
        self.previous: np.ndarray | None = None  # each row's last executed action
        self.acted_before, self.reached_before = np.zeros((rows, width), bool), np.zeros((rows, width), bool)
        self.dims = 0

    def record(self, rows: np.ndarray, action: np.ndarray, reward: np.ndarray, decided: np.ndarray,
               sizes: np.ndarray, reached: np.ndarray) -> None:
        """One base step in the `rows` mask: the executed `action` ([rows, A]), `reward`, which layers `decided`
        ([rows, layers]), each layer's mean |contribution| (`StepRecord.size`, [rows, layers]) and which layers the
        walk `reached` ([rows, layers])."""
        action = np.asarray(action, np.float64)
        if self.previous is None:
            self.previous, self.dims = np.zeros_like(action), action.shape[1]
        later = rows & (self.steps > 0)
        repeated = later & np.all(action == self.previous, axis=1)
        self.repeats += repeated
        self.bound_repeats += repeated & at_bounds(action, self.bounds)
        acted = sizes > 0
        self.held_repeats += later & held(decided, acted, reached, self.acted_before, self.reached_before)
        self.acted_before = np.where(rows[:, None], acted, self.acted_before)
        self.reached_before = np.where(rows[:, None], reached, self.reached_before)
        self.change += np.where(later, np.abs(action - self.previous).sum(axis=1), 0.0)
        self.previous = np.where(rows[:, None], action, self.previous)
        self.ret += np.where(rows, reward, 0.0)
        self.steps += rows
        decided = decided & rows[:, None]
        self.decisions += decided.any(axis=1)
        self.compute += decided.astype(np.int64) @ self.macs
        self.decided += decided
        self.acted += acted & rows[:, None]
        self.contribution += np.where(rows[:, None], sizes, 0.0)

    def finish(self, row: int) -> EpisodeMeasures:
        """The measures of the episode in `row`, which starts over."""
        measures = _measures(self.layers, self.ret[row], int(self.steps[row]), int(self.repeats[row]),
                             int(self.bound_repeats[row]), int(self.held_repeats[row]), self.change[row], self.dims,
                             int(self.decisions[row]), int(self.compute[row]), self.decided[row], self.acted[row],
                             self.contribution[row])
        for counts in (self.ret, self.steps, self.repeats, self.bound_repeats, self.held_repeats, self.change,
                       self.decisions, self.compute, self.decided, self.acted, self.contribution):
            counts[row] = 0
        return measures


@dataclass(frozen=True)
class Evaluation:
    """Means over the episodes of one evaluation (activity as shares of steps)."""

    return_mean: float
    return_std: float
    repetition: float
    jerk: float
    decisions: float
    compute: float
    steps: float
    decided: dict[str, float]
    acted: dict[str, float]
    contribution: dict[str, float]  # mean |contribution| per step, averaged over action dimensions
    return_min: float = float("nan")  # the lowest and highest episode return
    return_max: float = float("nan")
    repetition_at_bounds: float = float("nan")  # (NaN in the curves of checkpoints taken before it was measured)
    repetition_held: float = float("nan")  # (likewise)

    PER_LAYER: ClassVar[tuple[str, ...]] = ("decided", "acted", "contribution")

    def row(self) -> dict[str, float]:
        """Flat columns for a CSV row: the stack's measures, then per-layer ones as `<measure>_<layer>`."""
        out = {
            "return_mean": self.return_mean, "return_std": self.return_std, "return_min": self.return_min,
            "return_max": self.return_max, "repetition": self.repetition,
            "repetition_at_bounds": self.repetition_at_bounds, "repetition_held": self.repetition_held,
            "jerk": self.jerk, "decisions": self.decisions, "compute": self.compute, "episode_steps": self.steps,
        }
        for measure in self.PER_LAYER:
            out |= {f"{measure}_{n}": v for n, v in getattr(self, measure).items()}
        return out

    @classmethod
    def columns(cls, layers: Sequence[str]) -> list[str]:
        """Every column `row` can give for a stack of `layers`, in its order."""
        stack = ["return_mean", "return_std", "return_min", "return_max", "repetition", "repetition_at_bounds",
                 "repetition_held", "jerk", "decisions", "compute", "episode_steps"]
        return stack + [f"{measure}_{n}" for measure in cls.PER_LAYER for n in layers]


def summarise(episodes: Sequence[EpisodeMeasures]) -> Evaluation:
    """Average the measures of several episodes; per-layer activity is pooled over all their steps."""
    total = sum(e.steps for e in episodes)
    names = list(episodes[0].decided)
    returns = np.array([e.ret for e in episodes])
    return Evaluation(
        return_mean=float(returns.mean()),
        return_std=float(returns.std()),
        repetition=float(np.mean([e.repetition for e in episodes])),
        repetition_at_bounds=float(np.mean([e.repetition_at_bounds for e in episodes])),
        repetition_held=float(np.mean([e.repetition_held for e in episodes])),
        jerk=float(np.mean([e.jerk for e in episodes])),
        decisions=float(np.mean([e.decisions for e in episodes])),
        compute=float(np.mean([e.compute for e in episodes])),
        steps=float(np.mean([e.steps for e in episodes])),
        decided={n: sum(e.decided[n] for e in episodes) / total for n in names},
        acted={n: sum(e.acted[n] for e in episodes) / total for n in names},
        contribution={n: sum(e.contribution[n] for e in episodes) / total for n in names},
        return_min=float(returns.min()),
        return_max=float(returns.max()),
    )
