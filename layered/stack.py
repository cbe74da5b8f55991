"""The layer stack: who acts at base step t, what each layer sees, how held outputs merge.

Layers are ordered slowest first. Layer i decides at the base steps that are multiples of its
period and holds its output in between. A committed gate above a layer stops it from being
evaluated; a layer absent from the current phase contributes nothing and never decides.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from gymnasium.spaces import Box

from layered.buffer import Transition
from layered.combiners import COMBINERS, Combiner, Route
from layered.envs import env_info
from layered.outputs import OutputLayout

if TYPE_CHECKING:  # the recipe module validates stacks with the rules below, so it imports this one
    from layered.recipe import Recipe


def combiner_kind(recipe: Recipe, i: int) -> str | None:
    """The combiner merging layer i with the layers below it; the fastest layer has none below, so none."""
    if i == len(recipe.layers) - 1:
        return None
    return recipe.layers[i].combine or recipe.combine.kind


def reward_per_step(recipe: Recipe) -> float | None:
    """The environment's return range per step, (best - worst return) / episode steps, if known."""
    info = env_info(recipe.env.id)
    return_range = recipe.return_range()
    if return_range is None or not info.episode_steps:
        return None
    return (return_range[1] - return_range[0]) / info.episode_steps


def action_penalty(recipe: Recipe, i: int) -> float:
    """Layer i's action penalty in reward units (see `action_penalty_unit`)."""
    layer = recipe.layers[i]
    if layer.action_penalty_unit == "reward":
        return layer.action_penalty
    scale = reward_per_step(recipe)
    assert scale is not None, "recipes are checked to know the return range per step"
    return layer.action_penalty * scale


def output_layout(recipe: Recipe, i: int, action_dims: int) -> OutputLayout:
    """What layer i outputs: the env's action dims, its combiner's gate dims, and a repeat count if it repeats."""
    kind = combiner_kind(recipe, i)
    gate_dims = COMBINERS.get(kind).gate_dims if kind is not None else 0
    return OutputLayout(action_dims, gate_dims, recipe.layers[i].max_repeat)


@dataclass(frozen=True)
class Layer:
    """One layer as the stack runs it."""

    name: str
    period: int
    sees: tuple[int, ...]  # indices of slower layers whose held actions extend the observation
    combiner: Combiner | None  # None for the fastest layer: it has no layer below to merge with
    layout: OutputLayout
    action_space: Box  # bounds of each entry of the layout
    half_range: np.ndarray  # half-width of the layer's action dims, for the action penalty
    action_penalty: float
    defer_reward_scale: tuple[float, float]
    defer_penalty: float
    deviation_penalty: float
    delay: int  # decisions between choosing an output and its taking effect
    learns_from_commits: bool  # training only: decides under a committed gate, taking the executed action
    gamma: float  # the layer's discount per decision (or per base step)
    discount_per_step: bool  # True: a decision spanning k base steps is discounted by gamma**k

    def repeats(self, output: np.ndarray) -> int:
        """For how many of its periods the layer holds `output` before deciding again."""
        return int(np.clip(np.rint(output[-1]), 1, self.layout.max_repeat)) if self.layout.repeats else 1

    def discount(self, elapsed: int) -> float:
        """The discount of the bootstrap value after a decision that spanned `elapsed` base steps."""
        return self.gamma**elapsed if self.discount_per_step else self.gamma


@dataclass
class Decision:
    """A layer's latest decision and what has followed it so far: the makings of its next transition."""

    seen: np.ndarray
    output: np.ndarray
    elapsed: int = 0  # base steps since the decision
    path: list[tuple[np.ndarray, float]] = field(default_factory=list)  # repeating layers: per period
    period_reward: float = 0.0  # repeating layers: reward of the period under way


@dataclass(frozen=True)
class Composition:
    """The executed action at one base step and each in-effect layer's contribution to it."""

    action: np.ndarray
    contributions: dict[int, np.ndarray]  # layers reached by the walk; zeros for a deferring gate
    routes: dict[int, Route]


def _layer_action_space(recipe: Recipe, i: int, env_space: Box, layout: OutputLayout) -> Box:
    """Env bounds scaled about their centre (a residual layer's centred on zero), then any gate
    dimensions in [-1, 1], then, for a layer that may repeat, the repeat count in [1, max_repeat]."""
    low, high = env_space.low.astype(np.float64), env_space.high.astype(np.float64)
    half = (high - low) / 2 * recipe.layers[i].action_scale
    residual = i > 0 and output_layout(recipe, i - 1, layout.action_dims).gate_dims == 0
    mid = np.zeros_like(low) if residual else (high + low) / 2
    low, high = mid - half, mid + half
    if layout.gate_dims:
        low, high = np.append(low, -np.ones(layout.gate_dims)), np.append(high, np.ones(layout.gate_dims))
    if layout.repeats:
        low, high = np.append(low, 1.0), np.append(high, float(layout.max_repeat))
    return Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)


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
        self.action_dim = int(action_space.shape[0])
        self.low = action_space.low.astype(np.float32)
        self.high = action_space.high.astype(np.float32)
        self.env_half = env_half = (self.high - self.low) / 2
        self.layers: list[Layer] = []
        for i, cfg in enumerate(recipe.layers):
            kind = combiner_kind(recipe, i)
            fraction = threshold if threshold is not None else recipe.threshold(i)
            absolute = fraction * env_half if evaluation and fraction > 0 else None
            combiner = None if kind is None else COMBINERS.get(kind)(absolute, recipe.combine.per_dimension)
            layout = output_layout(recipe, i, self.action_dim)
            space = _layer_action_space(recipe, i, action_space, layout)
            self.layers.append(Layer(
                name=cfg.name,
                period=int(cfg.period or 0),
                sees=tuple(names.index(s) for s in cfg.sees if s != "obs"),
                combiner=combiner,
                layout=layout,
                action_space=space,
                half_range=((space.high - space.low) / 2)[: self.action_dim],
                action_penalty=action_penalty(recipe, i),
                defer_reward_scale=cfg.defer_reward_scale,
                defer_penalty=cfg.defer_penalty,
                deviation_penalty=cfg.deviation_penalty,
                delay=cfg.delay,
                learns_from_commits=cfg.learn_from_commits and not evaluation,
                gamma=recipe.learner_config(i).gamma,
                discount_per_step=recipe.train.discount == "step",
            ))
        wanted = names if active is None else list(active)
        unknown = [n for n in wanted if n not in names]
        if unknown or not wanted:
            raise ValueError(f"active layers {wanted} must be a non-empty subset of {names}")
        self.active = [i for i, n in enumerate(names) if n in wanted]
        self.observation_spaces = [self._observation_space(obs_space, layer) for layer in self.layers]
        self.held = [np.zeros(layer.action_space.shape, np.float32) for layer in self.layers]
        # outputs chosen but not yet in effect, oldest first (the real-time setting)
        self.inflight = [np.zeros((layer.delay, *layer.action_space.shape), np.float32) for layer in self.layers]
        self.resume_at = [0] * len(self.layers)  # the first step a repeating layer may decide again
        self.decisions: list[Decision | None] = [None] * len(self.layers)  # this episode's latest, per layer
        self.t = 0

    def _observation_space(self, obs_space: Box, layer: Layer) -> Box:
        lows, highs = [obs_space.low.ravel()], [obs_space.high.ravel()]
        for j in layer.sees:  # a held action is zero before the first decision, so 0 is included
            space = self.layers[j].action_space
            lows.append(np.minimum(space.low[: self.action_dim], 0))
            highs.append(np.maximum(space.high[: self.action_dim], 0))
        own = layer.action_space
        lows += [np.minimum(own.low, 0)] * layer.delay  # its own outputs in flight
        highs += [np.maximum(own.high, 0)] * layer.delay
        return Box(np.concatenate(lows).astype(np.float32), np.concatenate(highs).astype(np.float32), dtype=np.float32)

    def reset(self) -> None:
        """Start an episode: step 0, every held output zero."""
        self.t = 0
        self.resume_at = [0] * len(self.layers)
        self.decisions = [None] * len(self.layers)
        for out in (*self.held, *self.inflight):
            out.fill(0.0)

    def observation(self, i: int, obs: np.ndarray) -> np.ndarray:
        """What layer i sees before its next decision: the env observation; of each slower layer it
        names, the output that will be in effect when i's output takes effect (with delays, not
        necessarily the one held now); and, when it acts with a delay, its own outputs in flight
        (oldest first) as they will be executed: their action part is the contribution each will
        make when it lands, after thresholds and gates (zero where a gate above commits)."""
        layer = self.layers[i]
        lands = self.upcoming(i) + layer.delay * layer.period
        parts = [np.asarray(obs, np.float32).ravel()]
        parts += [self.in_effect(j, lands)[: self.action_dim] for j in layer.sees]
        parts += [self._as_executed(i, k) for k in range(layer.delay)]
        return np.concatenate(parts)

    def upcoming(self, j: int) -> int:
        """The step of layer j's next decision on its schedule (now, if it is due and has not decided)."""
        period = self.layers[j].period
        return max(-(-self.t // period) * period, self.resume_at[j])

    def in_effect(self, j: int, step: int) -> np.ndarray:
        """Layer j's output in effect at base `step` (>= now) as far as j has decided: the held one
        until its next decision, then its outputs in flight in turn, then the newest of them."""
        queue, period, upcoming = self.inflight[j], self.layers[j].period, self.upcoming(j)
        if step < upcoming or not len(queue):
            return self.held[j]
        return queue[min((step - upcoming) // period, len(queue) - 1)]

    def _as_executed(self, i: int, k: int) -> np.ndarray:
        """Layer i's k-th output in flight with its action part replaced by the contribution it will
        make when it lands, composed with the outputs the other layers will then have in effect."""
        lands = self.upcoming(i) + k * self.layers[i].period
        entry = self.inflight[i][k]
        outputs = [entry if j == i else self.in_effect(j, lands) for j in range(len(self.layers))]
        executed = self._walk(outputs).contributions.get(i, np.zeros(self.action_dim, np.float32))
        return np.concatenate([executed, entry[self.action_dim:]])

    def _route(self, position: int, i: int, output: np.ndarray) -> Route:
        # The fastest present layer has no one below in this phase: its output just joins the sum.
        if position == len(self.active) - 1:
            return Route.ADD
        combiner = self.layers[i].combiner
        assert combiner is not None, "only the fastest layer has no combiner, and it is always last"
        return combiner.route(output[: self.action_dim + combiner.gate_dims])

    def next_due(self, start: int = 0) -> int | None:
        """The first present layer with index >= start that decides at the current step, if any.
        Below a committed gate none does, except a layer right below it that learns from commits."""
        for position, i in enumerate(self.active):
            if i >= start and self._due(i):
                return i
            if self._route(position, i, self.held[i]) is Route.COMMIT:  # never the last layer: it only adds
                below = self.active[position + 1]
                learns = below >= start and self.layers[below].learns_from_commits
                return below if learns and self._due(below) else None
        return None

    def _due(self, i: int) -> bool:
        return self.t % self.layers[i].period == 0 and self.t >= self.resume_at[i]

    def decide(self, i: int, seen: np.ndarray, output: np.ndarray) -> None:
        """Layer i, having observed `seen`, chose `output`: hold it and start its next transition.
        Under a committed gate (a layer that learns from commits) the executed action is recorded
        instead: the output that, had the gate deferred, would have been executed."""
        if self.layers[i].learns_from_commits and i not in (composition := self.compose()).contributions:
            output = self._executed_as_output(i, composition)
        self.decisions[i] = Decision(seen, output)
        self.hold(i, output)

    def _executed_as_output(self, i: int, composition: Composition) -> np.ndarray:
        """What layer i, kept out by the committed gate right above it, would have had to output for
        the executed action had the gate deferred: that action less what the layers above the gate add."""
        gate = self.active[self.active.index(i) - 1]
        above = sum((c for j, c in composition.contributions.items() if j < gate), np.zeros(self.action_dim))
        space = self.layers[i].action_space
        return np.clip(composition.action - above, space.low, space.high).astype(np.float32)

    def hold(self, i: int, output: np.ndarray) -> None:
        """Layer i decided `output`; it is held until its next decision, or, with a delay of d,
        takes effect d decisions later while the oldest output in flight takes effect now."""
        layer = self.layers[i]
        space = layer.action_space
        output = np.clip(np.asarray(output, np.float32).reshape(space.shape), space.low, space.high)
        self.resume_at[i] = self.t + layer.repeats(output) * layer.period
        queue = self.inflight[i]
        if len(queue):
            output, queue[:-1], queue[-1] = queue[0].copy(), queue[1:].copy(), output
        self.held[i] = output

    def compose(self) -> Composition:
        """The executed action of this step: the present layers' held outputs, merged."""
        return self._walk(self.held)

    def _walk(self, outputs: Sequence[np.ndarray]) -> Composition:
        """Walk the present layers slowest first and merge `outputs` (one per layer) into the action."""
        total = np.zeros(self.action_dim, np.float32)
        contributions: dict[int, np.ndarray] = {}
        routes: dict[int, Route] = {}
        admit_by: Combiner | None = None
        for position, i in enumerate(self.active):
            own = outputs[i][: self.action_dim]
            if admit_by is not None:
                own = admit_by.admit(total, own, self.low, self.high)
            route = routes[i] = self._route(position, i, outputs[i])
            contributions[i] = np.zeros_like(own) if route is Route.DEFER else own
            total = total + contributions[i]
            if route is Route.COMMIT:
                break
            admit_by = self.layers[i].combiner
        return Composition(np.clip(total, self.low, self.high), contributions, routes)

    def layer_rewards(self, reward: float, composition: Composition) -> dict[int, float]:
        """Each present layer's shaped share of one base-step reward.

        A layer the walk reached pays its action penalty and its deviation penalty (how far the
        executed action is from the action proposed by the nearest deferring gate at or above
        it); a gate that deferred has the reward scaled (x2 when r <= 0, x0.5 when r > 0 by
        default) and pays its defer penalty. Layers below a committed gate get the plain
        reward: it still accrues to the transition from their last decision.
        """
        out: dict[int, float] = {}
        deferring = [i for i in self.active if composition.routes.get(i) is Route.DEFER]
        for i in self.active:
            layer, r = self.layers[i], float(reward)
            if composition.routes.get(i) is Route.DEFER:
                negative, positive = layer.defer_reward_scale
                r = r * (negative if r <= 0 else positive) - layer.defer_penalty
            if i in composition.contributions:
                r -= layer.action_penalty * float(np.mean(np.abs(composition.contributions[i]) / layer.half_range))
                gates = [k for k in deferring if k <= i] if layer.deviation_penalty else []
                if gates:
                    proposed = self.held[gates[-1]][: self.action_dim]
                    deviation = float(np.mean(np.abs(composition.action - proposed) / self.env_half))
                    r -= layer.deviation_penalty * deviation
            out[i] = r
        return out

    def record(self, rewards: dict[int, float], obs: np.ndarray, ended: bool) -> None:
        """Book the base step just executed (and ticked past) into each deciding layer's transition
        under way: one more step elapsed and, for a layer that repeats, (its observation, its
        reward) at the end of each of its periods (or of the episode). `rewards` are the step's
        `layer_rewards`."""
        for i, r in rewards.items():
            decision, layer = self.decisions[i], self.layers[i]
            if decision is None:
                continue
            decision.elapsed += 1
            if layer.layout.repeats:
                decision.period_reward += r
                if self.t % layer.period == 0 or ended:
                    decision.path.append((self.observation(i, obs), decision.period_reward))
                    decision.period_reward = 0.0

    def transition(self, i: int, reward: float, next_seen: np.ndarray, terminated: bool) -> Transition:
        """Layer i's completed transition since its latest decision this episode, given the shaped
        `reward` it accrued and what it sees now."""
        decision = self.decisions[i]
        assert decision is not None, f"layer {self.layers[i].name!r} has not decided yet this episode"
        discount = self.layers[i].discount(decision.elapsed)
        return Transition(decision.seen, decision.output, reward, next_seen, terminated, discount, tuple(decision.path))

    def tick(self) -> None:
        """Advance to the next base step."""
        self.t += 1
