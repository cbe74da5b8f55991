"""The paper's measures of a controller, from the base steps of evaluation episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np


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


def action_repetition(actions: Sequence[np.ndarray]) -> float:
    """Share of steps whose executed action equals the previous step's exactly (the first never does)."""
    if not actions:
        return 0.0
    repeats = sum(bool(np.array_equal(a, b)) for a, b in zip(actions[1:], actions[:-1], strict=True))
    return repeats / len(actions)


def jerk(actions: Sequence[np.ndarray]) -> float:
    """Mean absolute change of the executed action between consecutive steps, over steps and dimensions."""
    if len(actions) < 2:
        return 0.0
    return float(np.mean(np.abs(np.diff(np.asarray(actions, np.float64), axis=0))))


def normalised_auc(steps: Sequence[float], returns: Sequence[float], return_range: tuple[float, float]) -> float:
    """Trapezoidal area under the evaluation curve, returns mapped to [0, 1] by (worst, best),
    divided by the training span; a single evaluation gives its normalised return."""
    worst, best = return_range
    y = (np.asarray(returns, np.float64) - worst) / (best - worst)
    x = np.asarray(steps, np.float64)
    if len(x) < 2 or x[-1] == x[0]:
        return float(y[-1])
    return float(np.trapezoid(y, x) / (x[-1] - x[0]))


@dataclass(frozen=True)
class EpisodeMeasures:
    """One episode's return, length, action repetition, jerk, decisions, compute and per-layer activity."""

    ret: float
    steps: int
    repetition: float
    jerk: float
    decisions: int  # steps at which any layer's network was evaluated
    compute: int  # multiply-accumulates of every network evaluation
    decided: dict[str, int] = field(default_factory=dict)  # per layer: steps it was evaluated
    acted: dict[str, int] = field(default_factory=dict)  # per layer: steps its contribution was non-zero
    contribution: dict[str, float] = field(default_factory=dict)  # per layer: sum over steps of mean |c|


def measure_episode(trace: Sequence[StepRecord], macs: dict[str, int]) -> EpisodeMeasures:
    """Measures of one episode from its steps; `macs` is each layer's cost of one decision."""
    actions = [s.action for s in trace]
    return EpisodeMeasures(
        ret=float(sum(s.reward for s in trace)),
        steps=len(trace),
        repetition=action_repetition(actions),
        jerk=jerk(actions),
        decisions=sum(1 for s in trace if s.decided),
        compute=sum(macs[n] for s in trace for n in s.decided),
        decided={n: sum(n in s.decided for s in trace) for n in macs},
        acted={n: sum(s.size(n) > 0 for s in trace) for n in macs},
        contribution={n: float(sum(s.size(n) for s in trace)) for n in macs},
    )


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

    PER_LAYER: ClassVar[tuple[str, ...]] = ("decided", "acted", "contribution")

    def row(self) -> dict[str, float]:
        """Flat columns for a CSV row: the stack's measures, then per-layer ones as `<measure>_<layer>`."""
        out = {
            "return_mean": self.return_mean, "return_std": self.return_std, "return_min": self.return_min,
            "return_max": self.return_max, "repetition": self.repetition,
            "jerk": self.jerk, "decisions": self.decisions, "compute": self.compute, "episode_steps": self.steps,
        }
        for measure in self.PER_LAYER:
            out |= {f"{measure}_{n}": v for n, v in getattr(self, measure).items()}
        return out

    @classmethod
    def columns(cls, layers: Sequence[str]) -> list[str]:
        """Every column `row` can give for a stack of `layers`, in its order."""
        stack = ["return_mean", "return_std", "return_min", "return_max", "repetition", "jerk", "decisions", "compute",
                 "episode_steps"]
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
