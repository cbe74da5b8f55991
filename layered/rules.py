"""The per-step rules of a layer stack, written once over a batch of K independent stacks.

Layers are ordered slowest first. Layer j decides at the base steps that are multiples of its
period (and, if it repeats, not before the step its repeat count reaches); it holds its output in
between, or, with a delay of d decisions, its output takes effect d decisions later. A committed
gate above a layer stops it from being evaluated; a layer absent from the present ones contributes
nothing and never decides. What a layer sees, how held outputs merge through the combiners into
the executed action, and what each layer is paid for a base step are rules of this module too.

Row k of every array is a stack of its own: its episode clock, held outputs, gate state and outputs
in flight. What differs between rows (a reset, a layer due, a gate committing) is a mask, never a
loop over rows; K = 1 is one stack. Training, evaluation and the PettingZoo view (`layered.stack`)
and the exported runtime (`layered.runtime`) all step stacks through `Rules`.

numpy only, with relative imports: `layered export` copies this file beside the exported runtime,
so that an exported stack runs by these very rules without the library.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .combiners import Combiner, Route, clip, combiner_from_json

FORMAT = 2  # of the rules' JSON description (`Rules.to_json`); the runtime refuses another
ADD, COMMIT, DEFER = int(Route.ADD), int(Route.COMMIT), int(Route.DEFER)  # plain ints: enum lookups are slow


@dataclass(frozen=True)
class Layer:
    """One layer as the rules run it: its schedule, output bounds, combiner and reward shaping."""

    name: str
    period: int
    low: np.ndarray  # bounds of each entry of the layer's output (action, gate dims, repeat count)
    high: np.ndarray
    combiner: Combiner | None = None  # None for the fastest layer: it has no layer below to merge with
    sees: tuple[int, ...] = ()  # indices of slower layers whose outputs extend the observation
    delay: int = 0  # decisions between choosing an output and its taking effect
    max_repeat: int = 1  # above 1 the output's last entry is a repeat count in periods
    action_penalty: float = 0.0  # the shaping below is training's; an exported stack needs none of it
    defer_reward_scale: tuple[float, float] = (1.0, 1.0)
    defer_penalty: float = 0.0
    deviation_penalty: float = 0.0
    learns_from_commits: bool = False  # decides under a committed gate, taking the executed action
    sees_in_flight: bool = False  # beside each output in flight, the outputs of the layers it sees acting with it
    sees_executed: bool = False  # each output in flight shown as the action executed when it lands, not its part
    penalty_from_decision: bool = False  # with a delay: the action penalty on the newest output, from its decision
    half_range: np.ndarray = field(init=False)  # half-width of each output entry, for the action penalty

    def __post_init__(self) -> None:
        object.__setattr__(self, "half_range", (self.high - self.low) / 2)

    @property
    def size(self) -> int:
        """Length of the layer's output vector."""
        return len(self.low)

    @property
    def lag(self) -> int:
        """Base steps from a decision to its output's landing: `delay` of the layer's periods."""
        return self.delay * self.period

    def repeats(self, outputs: np.ndarray) -> np.ndarray | int:
        """For how many of its periods the layer holds each of `outputs` ([K, size]) before deciding again."""
        if self.max_repeat <= 1:
            return 1
        return np.clip(np.rint(outputs[:, -1]), 1, self.max_repeat).astype(np.int64)

    def to_json(self) -> dict[str, Any]:
        """What an exported stack needs of the layer, as plain JSON values."""
        return {"name": self.name, "period": self.period, "delay": self.delay, "sees": list(self.sees),
                "sees_in_flight": self.sees_in_flight, "sees_executed": self.sees_executed,
                "max_repeat": self.max_repeat, "low": [float(x) for x in self.low],
                "high": [float(x) for x in self.high],
                "combiner": None if self.combiner is None else self.combiner.to_json()}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Layer:
        """The layer `to_json` described (without training's reward shaping)."""
        combiner = None if data["combiner"] is None else combiner_from_json(data["combiner"])
        return cls(data["name"], int(data["period"]), np.asarray(data["low"], np.float32),
                   np.asarray(data["high"], np.float32), combiner, tuple(data["sees"]), int(data["delay"]),
                   int(data["max_repeat"]), sees_in_flight=bool(data.get("sees_in_flight", False)),
                   sees_executed=bool(data.get("sees_executed", False)))


@dataclass(frozen=True)
class Composition:
    """The executed actions of one base step over the batch, and how each present layer took part."""

    action: np.ndarray  # [K, action dims], clipped to the bounds
    contributions: dict[int, np.ndarray]  # [K, action dims] per present layer: zero where deferring or not
    # reached; they may share memory with the held outputs, which the next decision overwrites: copy to keep
    routes: dict[int, np.ndarray]  # [K] Route codes per present layer
    reached: dict[int, np.ndarray]  # [K] bool per present layer: no committed gate above it


Act = Callable[[int, np.ndarray, np.ndarray], np.ndarray]
"""A policy callback for `Rules.decide_all`: (layer, observations of the deciding rows, rows mask) -> outputs."""


class Rules:
    """K stacks of the same layers stepping together: their clocks, held outputs and outputs in flight."""

    def __init__(self, layers: Sequence[Layer], active: Sequence[int], low: np.ndarray, high: np.ndarray,
                 rows: int = 1) -> None:
        """`active`: indices of the present layers; `low`, `high`: the environment's action bounds."""
        if not active or sorted(set(active)) != list(active) or not 0 <= active[0] <= active[-1] < len(layers):
            raise ValueError(f"active layers {list(active)} must be increasing indices of the {len(layers)} layers")
        self.layers = list(layers)
        self.active = list(active)
        self.low = np.asarray(low, np.float32)
        self.high = np.asarray(high, np.float32)
        self.env_half = (self.high - self.low) / 2
        self.action_dim = len(self.low)
        self.rows = rows
        self._all = np.ones(rows, bool)
        self._index = np.arange(rows)
        self._adds = np.full(rows, ADD, np.int8)  # the route of a layer that only adds (never written to)
        self._none = np.zeros(rows, bool)  # (never written to)
        self.t = np.zeros(rows, np.int64)
        self.held = [np.zeros((rows, layer.size), np.float32) for layer in self.layers]
        self.inflight = [np.zeros((rows, layer.delay, layer.size), np.float32) for layer in self.layers]
        self.resume_at = [np.zeros(rows, np.int64) for _ in self.layers]  # the first step a repeating layer may decide
        self.decided = [np.zeros((rows, layer.size), np.float32) for layer in self.layers]  # as `decide` returned them

    def to_json(self) -> dict[str, Any]:
        """The layers, the present ones and the action bounds, as plain JSON values (`from_json` reads them)."""
        return {"format": FORMAT, "layers": [layer.to_json() for layer in self.layers],
                "active": [self.layers[i].name for i in self.active],
                "action_low": [float(x) for x in self.low], "action_high": [float(x) for x in self.high]}

    @classmethod
    def from_json(cls, data: dict[str, Any], rows: int = 1) -> Rules:
        """Rules for `rows` stacks as `to_json` described them."""
        if data.get("format") != FORMAT:
            raise ValueError(f"stack rules of format {data.get('format')!r}; these rules read format {FORMAT}")
        layers = [Layer.from_json(layer) for layer in data["layers"]]
        names = [layer.name for layer in layers]
        return cls(layers, [names.index(name) for name in data["active"]], np.asarray(data["action_low"]),
                   np.asarray(data["action_high"]), rows)

    def state_dict(self) -> dict[str, list[np.ndarray] | np.ndarray]:
        """Where every row stands (clocks, held outputs, outputs in flight, decisions), to continue exactly."""
        return {"t": self.t.copy(), "held": [h.copy() for h in self.held],
                "inflight": [f.copy() for f in self.inflight], "resume_at": [r.copy() for r in self.resume_at],
                "decided": [d.copy() for d in self.decided]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Put every row where `state_dict` found it."""
        self.t[:] = state["t"]
        for name in ("held", "inflight", "resume_at", "decided"):
            for mine, saved in zip(getattr(self, name), state[name], strict=True):
                mine[:] = saved

    def observation_bounds(self, i: int, obs_low: np.ndarray, obs_high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of what layer i sees (see `observation`), given the environment's observation bounds."""
        layer = self.layers[i]
        lows, highs = [np.ravel(obs_low)], [np.ravel(obs_high)]
        seen_lows = [np.minimum(self.layers[j].low[: self.action_dim], 0) for j in layer.sees]  # an output is zero
        seen_highs = [np.maximum(self.layers[j].high[: self.action_dim], 0) for j in layer.sees]  # before it decides
        lows += seen_lows
        highs += seen_highs
        own_low, own_high = layer.low.copy(), layer.high.copy()
        if layer.sees_executed:  # (an output in flight shown as the executed action)
            own_low[: self.action_dim], own_high[: self.action_dim] = self.low, self.high
        for _ in range(layer.delay):  # its own outputs in flight, each with what will act beside it
            lows += [np.minimum(own_low, 0), *(seen_lows if layer.sees_in_flight else [])]
            highs += [np.maximum(own_high, 0), *(seen_highs if layer.sees_in_flight else [])]
        return np.concatenate(lows).astype(np.float32), np.concatenate(highs).astype(np.float32)

    def reset(self, rows: np.ndarray | None = None) -> None:
        """Start an episode in the `rows` (a mask; default all): step 0, every held output and output in flight zero."""
        rows = self._all if rows is None else rows
        self.t[rows] = 0
        for resume_at, held, inflight in zip(self.resume_at, self.held, self.inflight, strict=True):
            resume_at[rows] = 0
            held[rows] = 0.0
            inflight[rows] = 0.0

    def tick(self, rows: np.ndarray | None = None) -> None:
        """Advance the `rows` (a mask; default all) to their next base step."""
        self.t[self._all if rows is None else rows] += 1

    def due(self, j: int) -> np.ndarray:
        """[K] whether layer j's schedule has it decide at each row's current step."""
        return (self.t % self.layers[j].period == 0) & (self.t >= self.resume_at[j])

    def upcoming(self, j: int) -> np.ndarray:
        """[K] the step of layer j's next decision on its schedule (now, if it is due and has not decided)."""
        period = self.layers[j].period
        return np.maximum(-(-self.t // period) * period, self.resume_at[j])

    def route(self, position: int, j: int, outputs: np.ndarray) -> np.ndarray:
        """[K] what layer j's `outputs` do to the walk, j being the `position`-th present layer. The
        fastest present layer has no one below in this phase: its output just joins the sum."""
        combiner = self.layers[j].combiner
        if position == len(self.active) - 1 or combiner is None:
            return self._adds
        return combiner.route(outputs[:, : self.action_dim + combiner.gate_dims])

    def next_due(self, start: int | np.ndarray = 0) -> np.ndarray:
        """[K] the first present layer with index >= start (per row) that decides at the current step,
        or -1. Below a committed gate none does, except a layer right below it that learns from commits."""
        result = np.full(self.rows, -1, np.int64)
        open_ = self._all.copy()  # rows still walking down the stack
        for position, i in enumerate(self.active):
            eligible = i >= start  # a bool for one start, a mask for a start per row
            if eligible is not False:
                hit = open_ & self.due(i) if eligible is True else open_ & eligible & self.due(i)
                result[hit] = i
                open_ &= ~hit
                if not _any(open_):
                    break
            route = self.route(position, i, self.held[i])
            commits = open_ & (route == COMMIT) if _any(route) else self._none  # (ADD is 0)
            if _any(commits):  # never the last layer: it only adds
                below = self.active[position + 1]
                if self.layers[below].learns_from_commits:
                    result[commits & (below >= start) & self.due(below)] = below
                open_ &= ~commits
        return result

    def in_effect(self, j: int, step: np.ndarray) -> np.ndarray:
        """[K, size] layer j's output in effect at base `step` ([K], >= now) as far as j has decided: the
        held one until its next decision, then its outputs in flight in turn, then the newest of them."""
        queue, held = self.inflight[j], self.held[j]
        if not queue.shape[1]:
            return held
        upcoming = self.upcoming(j)
        k = np.minimum(np.maximum((step - upcoming) // self.layers[j].period, 0), queue.shape[1] - 1)
        return np.where((step < upcoming)[:, None], held, queue[self._index, k])

    def observation(self, i: int, obs: np.ndarray) -> np.ndarray:
        """[K, ...] what layer i sees before its next decision, given the environment's observations
        `obs` ([K, ...]): the observation; of each slower layer it names, the output that will be in
        effect when i's output takes effect (with delays, not necessarily the one held now); and, when
        it acts with a delay, its own outputs in flight (oldest first) as they will be executed: their
        action part is the contribution each will make when it lands, after thresholds and gates (zero
        where a gate above commits), or with `sees_executed` the action the environment will execute then
        (with the other layers' outputs as far as they are decided), each followed, with `sees_in_flight`,
        by the outputs of the slower layers it names that will be in effect when it lands."""
        layer = self.layers[i]
        upcoming = self.upcoming(i)
        lands = upcoming + layer.lag
        parts = [np.asarray(obs, np.float32).reshape(self.rows, -1)]
        parts += [self.in_effect(j, lands)[:, : self.action_dim] for j in layer.sees]
        for k in range(layer.delay):
            at = upcoming + k * layer.period
            entry = self.inflight[i][:, k]
            outputs = [entry if j == i else self.in_effect(j, at) for j in range(len(self.layers))]
            composed = self.walk(outputs)
            parts += [composed.action if layer.sees_executed else composed.contributions[i], entry[:, self.action_dim:]]
            if layer.sees_in_flight:
                parts += [outputs[j][:, : self.action_dim] for j in layer.sees]
        return np.concatenate(parts, axis=1)

    def decide(self, i: int, outputs: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Layer i chose `outputs` ([K, size]; only the `rows` mask's count, default all): hold them, and
        return them as decided. In rows where a committed gate keeps it out (a layer that learns from
        commits) the decision is the executed action instead: the output that, had the gate deferred,
        would have been executed."""
        rows = self._all if rows is None else rows
        outputs = np.asarray(outputs, np.float32).reshape(self.rows, -1)
        if self.layers[i].learns_from_commits:
            composition = self.compose()
            kept_out = ~composition.reached[i]
            if _any(kept_out):
                outputs = np.where(kept_out[:, None], self._executed_as_output(i, composition), outputs)
        self.hold(i, outputs, rows)
        self.decided[i][...] = outputs if _every(rows) else np.where(rows[:, None], outputs, self.decided[i])
        return outputs

    def _executed_as_output(self, i: int, composition: Composition) -> np.ndarray:
        """[K, size] what layer i, kept out by the committed gate right above it, would have had to output
        for the executed action had the gate deferred: that action less what the layers above the gate add."""
        gate = self.active[self.active.index(i) - 1]
        above = np.zeros((self.rows, self.action_dim))
        for j in self.active:
            if j < gate:
                above = above + composition.contributions[j]
        layer = self.layers[i]
        return clip(composition.action - above, layer.low, layer.high).astype(np.float32)

    def hold(self, i: int, outputs: np.ndarray, rows: np.ndarray | None = None) -> None:
        """In the `rows` (a mask; default all), layer i decided `outputs` ([K, size]): each is held until
        its next decision, or, with a delay of d, takes effect d decisions later while the oldest output
        in flight takes effect now."""
        rows = self._all if rows is None else rows
        every = _every(rows)  # all rows: plain assignments (the common case at K = 1)
        layer = self.layers[i]
        outputs = clip(np.asarray(outputs, np.float32).reshape(self.rows, layer.size), layer.low, layer.high)
        resume_at = self.t + layer.repeats(outputs) * layer.period
        self.resume_at[i] = resume_at if every else np.where(rows, resume_at, self.resume_at[i])
        queue = self.inflight[i]
        if queue.shape[1]:
            landing = queue[:, 0].copy()
            shifted = np.concatenate([queue[:, 1:], outputs[:, None]], axis=1)
            queue[...] = shifted if every else np.where(rows[:, None, None], shifted, queue)
            outputs = landing
        self.held[i][...] = outputs if every else np.where(rows[:, None], outputs, self.held[i])

    def amend(self, i: int, age: int, outputs: np.ndarray) -> str:
        """Layer i's decision `age` decisions ago (0: its latest) was held or queued without its outputs,
        which came late (a layer deployed as a process of its own): put `outputs` ([K, size]) in its place.
        Still in flight, it lands as decided ('in flight'); landed and still held, it takes effect from now
        ('late'); older, a newer decision already replaced it and nothing changes ('stale')."""
        layer = self.layers[i]
        if age > layer.delay:
            return "stale"
        outputs = clip(np.asarray(outputs, np.float32).reshape(self.rows, layer.size), layer.low, layer.high)
        slot = self.held[i] if age == layer.delay else self.inflight[i][:, layer.delay - 1 - age]
        if age == 0:  # its repeat count sets when it decides next
            self.resume_at[i] += (layer.repeats(outputs) - layer.repeats(slot)) * layer.period
        slot[...] = outputs
        return "late" if age == layer.delay else "in flight"

    def decide_all(self, obs: np.ndarray, act: Act) -> dict[int, np.ndarray]:
        """Every decision of the current step in one pass down the stack, slowest layer first: each layer
        due in a row and not kept out there by a committed gate above it is given its observations and
        asked for its outputs by `act`. The same decisions as following `next_due` from each decision to
        the next (the layer right below a committed gate decides if it learns from commits, and none
        below it), in one pass instead of one walk per decision. The mask of deciding rows, per present layer."""
        decided = {}
        open_ = self._all  # rows in which no committed gate stands above this layer
        under = self._none  # rows in which the layer right above committed
        for position, i in enumerate(self.active):
            allowed = open_ | under if self.layers[i].learns_from_commits else open_
            rows = decided[i] = allowed & self.due(i)
            if _every(rows):
                self.decide(i, act(i, self.observation(i, obs), rows), rows)
            elif _any(rows):
                outputs = np.zeros((self.rows, self.layers[i].size), np.float32)
                outputs[rows] = act(i, self.observation(i, obs)[rows], rows)
                self.decide(i, outputs, rows)
            route = self.route(position, i, self.held[i])
            if _any(route):  # some row commits or defers (ADD is 0)
                under = open_ & (route == COMMIT)
                open_ = open_ & ~under
            else:
                under = self._none
        return decided

    def compose(self) -> Composition:
        """The executed actions of this step: the present layers' held outputs, merged."""
        return self.walk(self.held)

    def walk(self, outputs: Sequence[np.ndarray]) -> Composition:
        """Walk the present layers slowest first and merge `outputs` (one [K, size] per layer) into the
        actions: each layer's action, admitted by the combiner above it, joins the sum unless its route
        defers; a route that commits ends the walk in its row."""
        total = np.zeros((self.rows, self.action_dim), np.float32)
        contributions: dict[int, np.ndarray] = {}
        routes: dict[int, np.ndarray] = {}
        reached: dict[int, np.ndarray] = {}
        open_ = self._all
        admit_by: Combiner | None = None
        for position, i in enumerate(self.active):
            own = outputs[i][:, : self.action_dim]
            if admit_by is not None:
                own = admit_by.admit(total, own, self.low, self.high)
            route = routes[i] = self.route(position, i, outputs[i])
            reached[i] = open_
            if _any(route):  # some row commits or defers (ADD is 0)
                contributions[i] = np.where((open_ & (route != DEFER))[:, None], own, np.float32(0.0))
                open_ = open_ & (route != COMMIT)
            else:
                contributions[i] = own if open_ is self._all else np.where(open_[:, None], own, np.float32(0.0))
            total = total + contributions[i]
            admit_by = self.layers[i].combiner
        return Composition(clip(total, self.low, self.high), contributions, routes, reached)

    def layer_rewards(self, reward: np.ndarray, composition: Composition) -> dict[int, np.ndarray]:
        """Each present layer's shaped share ([K]) of one base step's rewards ([K]).

        A layer the walk reached pays its action penalty and its deviation penalty (how far the
        executed action is from the action proposed by the nearest deferring gate at or above it); a
        gate that deferred has the reward scaled (by default x2 when r <= 0, x0.5 when r > 0) and pays
        its defer penalty. Layers below a committed gate get the plain reward: it still accrues to the
        transition from their last decision.
        """
        reward = np.asarray(reward, np.float64)
        out: dict[int, np.ndarray] = {}
        proposed = np.zeros((self.rows, self.action_dim), np.float32)  # by the nearest deferring gate so far
        deferring = np.zeros(self.rows, bool)
        for i in self.active:  # (a penalty of 0 leaves r as it is: r - 0 * x == r for the finite x here)
            layer, reached, r = self.layers[i], composition.reached[i], reward
            defers = reached & (composition.routes[i] == DEFER)
            if _any(defers):
                negative, positive = layer.defer_reward_scale
                r = np.where(defers, reward * np.where(reward <= 0, negative, positive) - layer.defer_penalty, r)
                proposed = np.where(defers[:, None], self.held[i][:, : self.action_dim], proposed)
                deferring = deferring | defers
            if layer.action_penalty:
                paid = self.inflight[i][:, -1, : self.action_dim] if layer.penalty_from_decision and layer.delay \
                    else composition.contributions[i]
                size = _mean(np.abs(paid) / layer.half_range[: self.action_dim])
                r = np.where(reached, r - layer.action_penalty * size.astype(np.float64), r)
            if layer.deviation_penalty and _any(deferring):
                deviation = _mean(np.abs(composition.action - proposed) / self.env_half)
                r = np.where(reached & deferring, r - layer.deviation_penalty * deviation.astype(np.float64), r)
            out[i] = r
        return out


def _mean(x: np.ndarray) -> np.ndarray:
    """The mean over the last axis exactly as np.mean computes it (a float32 sum, divided by an integer count
    in float64 and cast back), without its overhead."""
    total = np.add.reduce(x, axis=-1)
    return np.true_divide(total, np.intp(x.shape[-1]), out=total, casting="unsafe")


def _any(mask: np.ndarray) -> bool:
    """Whether any row of `mask` is set; for one stack, without a reduction's overhead (the common case)."""
    return bool(mask[0]) if len(mask) == 1 else bool(mask.any())


def _every(mask: np.ndarray) -> bool:
    """Whether every row of `mask` is set; for one stack, without a reduction's overhead."""
    return bool(mask[0]) if len(mask) == 1 else bool(mask.all())
