"""The layer stack: who acts at base step t, what each layer sees, how held outputs merge.

Layers are ordered slowest first. Layer i decides at the base steps that are multiples of its
period and holds its output in between. A committed gate above a layer stops it from being
evaluated; a layer absent from the current phase contributes nothing and never decides.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from gymnasium.spaces import Box

from layered.combiners import COMBINERS, Combiner, Route
from layered.recipe import Recipe


@dataclass(frozen=True)
class Layer:
    """One layer as the stack runs it."""

    name: str
    period: int
    sees: tuple[int, ...]  # indices of slower layers whose held actions extend the observation
    combiner: Combiner
    action_space: Box  # what the layer outputs: action dims, then any gate dims
    half_range: np.ndarray  # half-width of the layer's action dims, for the action penalty
    action_penalty: float
    defer_reward_scale: tuple[float, float]
    defer_penalty: float
    deviation_penalty: float
    delay: int  # decisions between choosing an output and its taking effect
    max_repeat: int  # > 1: the output's last entry says for how many periods to hold it

    def repeats(self, output: np.ndarray) -> int:
        """For how many of its periods the layer holds `output` before deciding again."""
        return int(np.clip(np.rint(output[-1]), 1, self.max_repeat)) if self.max_repeat > 1 else 1


@dataclass(frozen=True)
class Composition:
    """The executed action at one base step and each in-effect layer's contribution to it."""

    action: np.ndarray
    contributions: dict[int, np.ndarray]  # layers reached by the walk; zeros for a deferring gate
    routes: dict[int, Route]


def _layer_action_space(recipe: Recipe, i: int, env_space: Box, gate_dims: int) -> Box:
    """Env bounds scaled about their centre (a residual layer's centred on zero), then any gate
    dimensions in [-1, 1], then, for a layer that may repeat, the repeat count in [1, max_repeat]."""
    low, high = env_space.low.astype(np.float64), env_space.high.astype(np.float64)
    half = (high - low) / 2 * recipe.layers[i].action_scale
    residual = i > 0 and COMBINERS.get(recipe.combiner_kind(i - 1)).gate_dims == 0
    mid = np.zeros_like(low) if residual else (high + low) / 2
    low, high = mid - half, mid + half
    if gate_dims:
        low, high = np.append(low, -np.ones(gate_dims)), np.append(high, np.ones(gate_dims))
    max_repeat = recipe.layers[i].max_repeat
    if max_repeat > 1:
        low, high = np.append(low, 1.0), np.append(high, float(max_repeat))
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
            kind = COMBINERS.get(recipe.combiner_kind(i))
            fraction = threshold if threshold is not None else recipe.threshold(i)
            absolute = fraction * env_half if evaluation and fraction > 0 else None
            combiner = kind(threshold=absolute, per_dimension=recipe.combine.per_dimension)
            space = _layer_action_space(recipe, i, action_space, kind.gate_dims)
            self.layers.append(Layer(
                name=cfg.name,
                period=int(cfg.period or 0),
                sees=tuple(names.index(s) for s in cfg.sees if s != "obs"),
                combiner=combiner,
                action_space=space,
                half_range=((space.high - space.low) / 2)[: self.action_dim],
                action_penalty=cfg.action_penalty,
                defer_reward_scale=cfg.defer_reward_scale,
                defer_penalty=cfg.defer_penalty,
                deviation_penalty=cfg.deviation_penalty,
                delay=cfg.delay,
                max_repeat=cfg.max_repeat,
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
        for out in (*self.held, *self.inflight):
            out.fill(0.0)

    def observation(self, i: int, obs: np.ndarray) -> np.ndarray:
        """What layer i sees: the env observation, the actions its named slower layers hold, and
        its own outputs still in flight (oldest first) when it acts with a delay."""
        parts = [np.asarray(obs, np.float32).ravel()]
        parts += [self.held[j][: self.action_dim] for j in self.layers[i].sees]
        parts.append(self.inflight[i].ravel())
        return np.concatenate(parts)

    def _route(self, position: int, i: int) -> Route:
        # The fastest present layer has no one below: its output always just joins the sum.
        if position == len(self.active) - 1:
            return Route.ADD
        layer = self.layers[i]
        return layer.combiner.route(self.held[i][: self.action_dim + layer.combiner.gate_dims])

    def next_due(self, start: int = 0) -> int | None:
        """The first present layer with index >= start that decides at the current step, if any."""
        for position, i in enumerate(self.active):
            if i >= start and self.t % self.layers[i].period == 0 and self.t >= self.resume_at[i]:
                return i
            if self._route(position, i) is Route.COMMIT:
                return None
        return None

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
        """Walk the present layers slowest first and merge their held outputs into the action."""
        total = np.zeros(self.action_dim, np.float32)
        contributions: dict[int, np.ndarray] = {}
        routes: dict[int, Route] = {}
        admit_by: Combiner | None = None
        for position, i in enumerate(self.active):
            own = self.held[i][: self.action_dim]
            if admit_by is not None:
                own = admit_by.admit(total, own, self.low, self.high)
            route = routes[i] = self._route(position, i)
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

    def tick(self) -> None:
        """Advance to the next base step."""
        self.t += 1
