"""The stack of a recipe as training, evaluation and the PettingZoo view run it: one stack at a time.

The rules themselves (who decides at base step t, holding, delays, what each layer sees, how held
outputs merge, what each layer is paid) are `layered.rules`, written over a batch of stacks; this
module builds them from a recipe and an environment's spaces and runs them for one stack (K = 1),
adding what only training keeps: each layer's latest decision, from which its transitions are made.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from gymnasium.spaces import Box

from layered.buffer import Transition
from layered.combiners import COMBINERS, Route
from layered.outputs import OutputLayout
from layered.schema import Recipe
from layered.rules import Composition as RowsComposition
from layered.rules import Layer as LayerRules
from layered.rules import Rules


@dataclass(frozen=True)
class Layer:
    """One layer as training runs it: its rules, what its output means, its space and its discount."""

    rules: LayerRules
    layout: OutputLayout
    action_space: Box  # bounds of each entry of the layout
    gamma: float  # the layer's discount per decision (or per base step)
    discount_per_step: bool  # True: a decision spanning k base steps is discounted by gamma**k

    @property
    def name(self) -> str:
        """The layer's name in the recipe."""
        return self.rules.name

    @property
    def period(self) -> int:
        return self.rules.period

    def discount_units(self, steps: int) -> int:
        """How many factors of gamma discount a value `steps` base steps later: one per decision, or one per step."""
        return steps if self.discount_per_step else 1

    def discount(self, elapsed: int) -> float:
        """The discount of the bootstrap value after a decision that spanned `elapsed` base steps."""
        return self.gamma ** self.discount_units(elapsed)

    def discounts(self, elapsed: np.ndarray) -> np.ndarray:
        """`discount` of each row's decision, which spanned `elapsed[k]` base steps."""
        return self.gamma ** np.where(self.discount_per_step, elapsed, 1)


@dataclass
class Decision:
    """A layer's latest decision and what has followed it so far: the makings of its next transition."""

    seen: np.ndarray
    output: np.ndarray
    elapsed: int = 0  # base steps since the decision
    path: list[tuple[np.ndarray, float, int]] = field(default_factory=list)  # repeating layers: per period
    period_reward: float = 0.0  # repeating layers: reward of the period under way
    period_steps: int = 0  # repeating layers: base steps of the period under way


@dataclass(frozen=True)
class Composition:
    """The executed action at one base step and each in-effect layer's contribution to it."""

    action: np.ndarray
    contributions: dict[int, np.ndarray]  # layers reached by the walk; zeros for a deferring gate
    routes: dict[int, Route]
    batch: RowsComposition  # the same, as the rules computed it (one row)


def output_bounds(recipe: Recipe, i: int, env_space: Box, layout: OutputLayout) -> tuple[np.ndarray, np.ndarray]:
    """Layer i's output bounds: the env's scaled about their centre (a residual's centred on zero), then any gate
    dimensions in [-1, 1], then, for a layer that may repeat, the repeat count in [1, max_repeat]."""
    low, high = env_space.low.astype(np.float64), env_space.high.astype(np.float64)
    half = (high - low) / 2 * recipe.layers[i].action_scale
    mid = np.zeros_like(low) if residual(recipe, i) else (high + low) / 2
    low, high = mid - half, mid + half
    if layout.gate_dims:
        low, high = np.append(low, -np.ones(layout.gate_dims)), np.append(high, np.ones(layout.gate_dims))
    if layout.repeats:
        low, high = np.append(low, 1.0), np.append(high, float(layout.max_repeat))
    return low.astype(np.float32), high.astype(np.float32)


def residual(recipe: Recipe, i: int) -> bool:
    """Whether layer i's output is a residual, added to the action of the layers above: below a combiner that takes
    residuals, or in the place of a layer whose output is one (below a gate that is itself a residual)."""
    above = recipe.combiner_kind(i - 1) if i > 0 else None
    return above is not None and (COMBINERS.get(above).residual_below or residual(recipe, i - 1))


def has_threshold(recipe: Recipe, active: Sequence[str]) -> bool:
    """Whether, in the stack of the `active` layers, some layer's contribution passes a combiner's evaluation
    threshold: what Fig. 2 varies. A present layer's combiner admits the next faster present layer's output
    (`rules.Rules.walk`), so the fastest present has none that acts."""
    present = [i for i, name in enumerate(recipe.layer_names()) if name in active]
    return any((kind := recipe.combiner_kind(i)) is not None and COMBINERS.get(kind).thresholded for i in present[:-1])


class Stack:
    """The layers of a recipe over one environment's spaces, with one episode's held outputs."""

    def __init__(
        self,
        recipe: Recipe,
        obs_space: Box,
        action_space: Box,
        active: Sequence[str] | None = None,
        evaluation: bool = False,
        threshold: float | None = None,
    ) -> None:
        """`active` names the layers present (default all); `evaluation` applies the thresholds,
        `threshold` (a fraction of the maximum action) replaces the recipe's at every level."""
        if not isinstance(action_space, Box) or not isinstance(obs_space, Box):
            raise TypeError("layers need Box observation and action spaces")
        names = recipe.layer_names()
        wanted = names if active is None else list(active)
        unknown = [n for n in wanted if n not in names]
        if unknown or not wanted:
            raise ValueError(f"active layers {wanted} must be a non-empty subset of {names}")
        action_dim = int(action_space.shape[0])
        env_half = (action_space.high.astype(np.float32) - action_space.low.astype(np.float32)) / 2
        self.layers: list[Layer] = []
        for i, cfg in enumerate(recipe.layers):
            kind = recipe.combiner_kind(i)
            combiner = None
            if kind is not None:
                cls = COMBINERS.get(kind)
                fraction = threshold if threshold is not None else recipe.threshold(i)
                applies = evaluation and cls.thresholded and fraction > 0
                combiner = cls(fraction * env_half if applies else None, recipe.combine.per_dimension)
            layout = recipe.output_layout(i, action_dim)
            low, high = output_bounds(recipe, i, action_space, layout)
            self.layers.append(Layer(
                rules=LayerRules(
                    name=cfg.name, period=recipe.period(i), low=low, high=high, combiner=combiner,
                    sees=tuple(names.index(s) for s in cfg.sees if s != "obs"), delay=cfg.delay,
                    max_repeat=cfg.max_repeat, action_penalty=recipe.action_penalty(i),
                    defer_reward_scale=cfg.defer_reward_scale, defer_penalty=cfg.defer_penalty,
                    deviation_penalty=cfg.deviation_penalty,
                    learns_from_commits=cfg.learn_from_commits and not evaluation,
                    sees_in_flight=bool(cfg.sees_in_flight), sees_executed=bool(cfg.sees_executed),
                    penalty_from_decision=cfg.action_penalty_from == "decision"),
                layout=layout,
                action_space=Box(low, high, dtype=np.float32),
                gamma=recipe.learner_config(i).gamma,
                discount_per_step=recipe.train.discount == "step",
            ))
        present = [i for i, name in enumerate(names) if name in wanted]
        self.rules = Rules([layer.rules for layer in self.layers], present, action_space.low, action_space.high)
        self.active = self.rules.active
        self.action_dim = self.rules.action_dim
        self.low, self.high = self.rules.low, self.rules.high
        self.observation_spaces = [Box(*self.rules.observation_bounds(i, obs_space.low, obs_space.high),
                                       dtype=np.float32) for i in range(len(self.layers))]
        self.decisions: list[Decision | None] = [None] * len(self.layers)  # this episode's latest, per layer

    @property
    def t(self) -> int:
        """The current base step of the episode."""
        return int(self.rules.t[0])

    @property
    def held(self) -> list[np.ndarray]:
        """Each layer's output in effect now."""
        return [held[0] for held in self.rules.held]

    def reset(self) -> None:
        """Start an episode: step 0, every held output zero."""
        self.rules.reset()
        self.decisions = [None] * len(self.layers)

    def observation(self, i: int, obs: np.ndarray) -> np.ndarray:
        """What layer i sees before its next decision (see `rules.Rules.observation`)."""
        return self.rules.observation(i, np.asarray(obs)[None])[0]

    def next_due(self, start: int = 0) -> int | None:
        """The first present layer with index >= start that decides at the current step, if any."""
        due = int(self.rules.next_due(start)[0])
        return None if due < 0 else due

    def decide(self, i: int, seen: np.ndarray, output: np.ndarray) -> None:
        """Layer i, having observed `seen`, chose `output`: hold it and start its next transition
        (under a committed gate, a layer that learns from commits records the executed action)."""
        self.decisions[i] = Decision(seen, self.rules.decide(i, np.asarray(output)[None])[0])

    def hold(self, i: int, output: np.ndarray) -> None:
        """Layer i decided `output`: it is held (or queued behind its outputs in flight)."""
        self.rules.hold(i, np.asarray(output)[None])

    def compose(self) -> Composition:
        """The executed action of this step: the present layers' held outputs, merged."""
        batch = self.rules.compose()
        reached = [i for i in self.active if batch.reached[i][0]]
        return Composition(batch.action[0], {i: batch.contributions[i][0] for i in reached},
                           {i: Route(int(batch.routes[i][0])) for i in reached}, batch)

    def layer_rewards(self, reward: float, composition: Composition) -> dict[int, float]:
        """Each present layer's shaped share of one base-step reward (see `rules.Rules.layer_rewards`)."""
        shares = self.rules.layer_rewards(np.array([reward]), composition.batch)
        return {i: float(r[0]) for i, r in shares.items()}

    def accrue(self, rewards: dict[int, float], obs: np.ndarray, ended: bool) -> None:
        """Book the base step just executed (and ticked past) into each deciding layer's transition
        under way: one more step elapsed and, for a layer that repeats, (its observation, its
        reward, the discount units of the period) at the end of each of its periods (or of the
        episode). `rewards` are the step's `layer_rewards`."""
        for i, r in rewards.items():
            decision, layer = self.decisions[i], self.layers[i]
            if decision is None:
                continue
            decision.elapsed += 1
            if layer.layout.repeats:
                decision.period_reward += r
                decision.period_steps += 1
                if self.t % layer.period == 0 or ended:
                    units = layer.discount_units(decision.period_steps)
                    decision.path.append((self.observation(i, obs), decision.period_reward, units))
                    decision.period_reward, decision.period_steps = 0.0, 0

    def transition(self, i: int, reward: float, next_seen: np.ndarray, terminated: bool) -> Transition:
        """Layer i's completed transition since its latest decision this episode, given the shaped
        `reward` it accrued and what it sees now."""
        decision = self.decisions[i]
        assert decision is not None, f"layer {self.layers[i].name!r} has not decided yet this episode"
        discount = self.layers[i].discount(decision.elapsed)
        return Transition(decision.seen, decision.output, reward, next_seen, terminated, discount, tuple(decision.path))

    def tick(self) -> None:
        """Advance to the next base step."""
        self.rules.tick()
