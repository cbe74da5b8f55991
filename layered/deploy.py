"""`layered deploy`: a trained stack with each layer in a process of its own, the environment on the clock.

The driver owns the environment and the stack's rules (the exported `Rules`, the very rules of
training, evaluation and the export). Base step t is due at T0 + t·h, h being the environment's
timestep divided by the speed. Whenever the rules have a layer decide, the driver sends that layer's
process what it sees. A layer without delay must answer by the end of that base step: the driver
waits for it until then. A layer with a delay of d decisions must answer by the start of the step
its output lands at, d of its decisions later; the driver goes on meanwhile. An answer that misses
its deadline is counted, the stack executes what was in effect (the layer's previous output held,
or queued, in its place), and the answer takes effect from the first base step after it arrives,
unless the layer has decided again meanwhile (`Rules.amend`). So the delayed setting's semantics
hold, but the delays now come from the clock.

`lockstep` has no clock: it runs base steps back to back, as fast as the layers answer, and waits
for every answer at once, so that it acts as `layered eval` acts.
A layer whose process dies, or leaves a request unanswered for one of its periods past the deadline,
is a fault: the stack goes on without it (`hold`: the fastest layer then adds nothing, a slower one's
last output stays in effect) or stops (`stop`).
"""

from __future__ import annotations

import multiprocessing.connection
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from layered.layer_process import PROTOCOL, Fault, LayerEnd, LayerFault, Link, Request
from layered.rules import Rules

STALL_FLOOR_S = 0.02  # the shortest stall a clocked layer is declared dead after: the OS may pause a process that long
UNCLOCKED_STALL_S = 2.0  # lockstep: how long an unanswered request may wait
FAULT_ACTIONS = ("hold", "stop")


@dataclass(frozen=True)
class Settings:
    """How a deployment runs: its clock, what is injected, what a fault does."""

    speed: float = 1.0  # times real time
    lockstep: bool = False  # no clock: every answer is waited for, as fast as the layers answer
    links: Mapping[str, Link] = field(default_factory=dict)  # per layer name
    faults: Mapping[str, Fault] = field(default_factory=dict)
    on_fault: str = "hold"

    @property
    def label(self) -> str:
        """A name for files and tables: `lockstep`, `1x`, `10x`, with the links it injects."""
        clock = "lockstep" if self.lockstep else f"{self.speed:g}x"
        links = [f"{name}={link}" for name, link in sorted(self.links.items()) if link.mean_s]
        return ",".join([clock, *links])


@dataclass(eq=False)  # compared by identity: two decisions are never the same one
class Decision:
    """One request to a layer and what became of it."""

    layer: int
    step: int  # the base step it decides for
    sent: float  # monotonic seconds
    deadline: float  # when it must have been answered (`Driver._deadline`)
    age: int = 0  # decisions of the layer since this one
    answered: float | None = None
    output: np.ndarray | None = None
    compute_s: float | None = None
    to_layer_s: float | None = None  # from sending to the layer's receipt, and from its reply to the answer
    back_s: float | None = None  # here (wall clocks: comparable where both ends share a machine's clock)
    sent_wall: float = 0.0
    landed: int | None = None  # the base step from which it took effect
    missed: bool = False  # not answered by its deadline
    unseen: bool = False  # asked while an output in flight it sees (`sees_in_flight`) was not yet answered

    @property
    def latency_s(self) -> float | None:
        """Seconds from sending the request to its answer; None while unanswered."""
        return None if self.answered is None else self.answered - self.sent


@dataclass
class Episode:
    """One deployed episode."""

    ret: float
    actions: np.ndarray  # [steps, action dims], as executed
    wall_s: float


class Stop(RuntimeError):
    """A fault under `on_fault="stop"`: the deployment ends."""


class Driver:
    """Steps an environment with the layers' processes under a clock, by the stack's rules."""

    def __init__(self, rules: Rules, processes: Mapping[int, LayerEnd], timestep: float, settings: Settings,
                 notify: Callable[[str], None] = print) -> None:
        self.rules, self.processes, self.settings, self.notify = rules, dict(processes), settings, notify
        self.clocked = not settings.lockstep
        self.h = timestep / settings.speed if self.clocked else 0.0
        self.decisions: list[Decision] = []  # every request, for the summary
        self.asked: dict[tuple[int, int, int], Decision] = {}  # the same, by layer, episode and step
        self.pending: dict[int, list[Decision]] = {i: [] for i in rules.active}  # not yet landed
        self.faults: list[str] = []
        self.dead: set[int] = set()
        self.stash: list[tuple[int, Any]] = []  # answers that came while another was awaited: applied next step
        # per layer, the requests sent and not yet answered, oldest first: a process answers in order, so an
        # answer settles every request before its own
        self.outstanding: dict[int, deque[Decision]] = {i: deque() for i in rules.active}
        self.heard: dict[int, float] = {}  # when each layer last answered (monotonic)
        self.episode = -1
        self.t = 0
        self.t0 = 0.0

    def play(self, env: gym.Env, seed: int) -> Episode:
        """One episode from `seed`: at each base step, every due layer is asked, the action composed and executed."""
        obs, _ = env.reset(seed=seed)
        self.rules.reset()
        self.episode += 1
        self.t, self.t0, total, actions = 0, time.monotonic(), 0.0, []
        for queue in self.pending.values():
            queue.clear()  # the previous episode's answers are ignored when they come
        while True:
            if self.clocked:
                self._listen(self.t0 + self.t * self.h)
            self._collect()
            self.rules.decide_all(np.asarray(obs, np.float32).reshape(1, -1), self._act)
            action = self.rules.compose().action[0]
            actions.append(action.copy())
            obs, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            self.rules.tick()
            self.t += 1
            if terminated or truncated:
                return Episode(total, np.asarray(actions), time.monotonic() - self.t0)

    def _deadline(self, i: int) -> float:
        """When layer i's decision of this step must have been answered: without delay, by the end of this
        step; with one, by the start of the step it lands at, when the step's first decisions are made."""
        if not self.clocked:
            return float("inf")
        layer = self.rules.layers[i]
        return self.t0 + (self.t + (layer.lag if layer.delay else 1)) * self.h

    def _stall_limit(self, i: int) -> float:
        """How long past its deadline (clocked) or since it was sent (lockstep) a request may go unanswered."""
        if not self.clocked:
            return UNCLOCKED_STALL_S
        return max(self.rules.layers[i].period * self.h, STALL_FLOOR_S)

    def _act(self, i: int, view: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """`Rules.decide_all`'s callback: ask layer i's process, and return its answer, or what is in effect."""
        layer = self.rules.layers[i]
        placeholder = (self.rules.held[i] if layer.delay == 0 else self.rules.inflight[i][:, -1]).copy()
        late = [d for d in self.pending[i] if d.missed and d.landed == self.t]  # put in place at this step's start
        for decision in self.pending[i]:
            self._age(decision)
        self.pending[i] = [d for d in self.pending[i] if d.landed is None and d.age <= layer.delay]
        if layer.delay:
            _never_executed(late)  # this decision moves the queue on: the next output in flight is held instead
        if i in self.dead or (layer.learns_from_commits and not self.rules.compose().reached[i][0]):
            return placeholder  # no process to ask, or kept out by a committed gate: the rules put the action there
        decision = Decision(i, self.t, time.monotonic(), self._deadline(i), sent_wall=time.time(),
                            unseen=self._unseen(i))
        self.decisions.append(decision)
        self.asked[i, self.episode, self.t] = decision
        self.pending[i].append(decision)
        if not self._ask(i, decision, Request(PROTOCOL, layer.name, self.episode, self.t, view[0], decision.sent_wall)):
            return placeholder
        if layer.delay and self.clocked:
            return placeholder  # its answer is put in its place in flight when it comes (`_take`)
        if self._wait(i, decision) and decision.output is not None:
            if layer.delay == 0:
                decision.landed = self.t
                _never_executed(late)  # replaced by this answer, on time, before any action was composed
            return decision.output.reshape(1, -1)
        decision.missed = True
        return placeholder

    def _unseen(self, i: int) -> bool:
        """Whether layer i is asked while a slower layer's output that it sees acting beside its own (`sees_in_flight`:
        one landing by the step its output lands at) is not yet answered, so that its view holds a stand-in there
        where the simulated setting shows the answer: an answer in time for its own deadline can come too late for
        the faster layers that see it."""
        layers = self.rules.layers
        if not layers[i].sees_in_flight:
            return False
        lands = self.t + layers[i].lag
        return any(d.output is None and d.step + layers[k].lag <= lands
                   for k in layers[i].sees for d in self.pending.get(k, ()))

    def _age(self, decision: Decision) -> None:
        """Layer's next decision: one older; reaching its delay, it lands now, or is missed if unanswered."""
        decision.age += 1
        if decision.age == self.rules.layers[decision.layer].delay:
            if decision.output is not None:
                decision.landed = self.t
            else:
                decision.missed = True

    def _ask(self, i: int, decision: Decision, request: Request) -> bool:
        try:
            self.processes[i].send(request)
            self.outstanding[i].append(decision)
            return True
        except LayerFault as e:
            self._fault(i, str(e))
            return False

    def _wait(self, i: int, decision: Decision) -> bool:
        """Take layer i's answers until `decision`'s comes (True) or its deadline passes (False); other
        answers that come meanwhile are kept to be applied at the next step."""
        limit = decision.sent + UNCLOCKED_STALL_S if not self.clocked else decision.deadline
        while decision.output is None:
            remaining = limit - time.monotonic()
            if remaining <= 0:
                if not self.clocked:
                    self._fault(i, f"layer {self.rules.layers[i].name!r} left step {decision.step}'s request "
                                   f"unanswered for {UNCLOCKED_STALL_S:g} s: stalled")
                return False
            try:
                reply = self._receive(i, min(remaining, 0.05))
            except LayerFault as e:
                self._fault(i, str(e))
                return False
            if reply is not None and reply.episode == self.episode and reply.step == decision.step:
                self._answer(decision, reply)
            elif reply is not None:
                self.stash.append((i, reply))
        return True

    def _receive(self, i: int, timeout_s: float) -> Any:
        """Layer i's next answer within `timeout_s`, or None; it settles the requests before it."""
        reply = self.processes[i].receive(timeout_s)
        if reply is not None:
            self.heard[i] = time.monotonic()
            answered, outstanding = self.asked.get((i, reply.episode, reply.step)), self.outstanding[i]
            while outstanding and outstanding.popleft() is not answered:
                pass
        return reply

    def _answer(self, decision: Decision, reply: Any) -> None:
        decision.answered = time.monotonic()
        decision.output = np.asarray(reply.output, np.float32)
        decision.compute_s = reply.compute_s
        decision.to_layer_s = reply.received - decision.sent_wall
        decision.back_s = time.time() - reply.replied

    def _collect(self) -> None:
        """Apply every answer that has come since the last step; notice processes that died or stalled."""
        for i, reply in self.stash:
            self._take(i, reply)
        self.stash.clear()
        now = time.monotonic()
        for i in self.rules.active:
            if i in self.dead or not self._drain(i):
                continue
            if not self.clocked or not self.outstanding[i]:
                continue
            oldest = self.outstanding[i][0]
            # stalled: silent for one of its periods since an overdue request's deadline, or its sending where
            # the driver ran late (answers that still come, however late, show a slow link, not a stall)
            if now - max(oldest.deadline, oldest.sent, self.heard.get(i, 0.0)) > self._stall_limit(i):
                self._fault(i, f"layer {self.rules.layers[i].name!r} left step {oldest.step}'s request unanswered "
                               f"and was silent for one of its periods past its deadline "
                               f"({self._stall_limit(i) * 1e3:.0f} ms): stalled")

    def _listen(self, until: float) -> None:
        """Until the monotonic time `until` (the next step), take each answer as it comes, so that its time
        of arrival is when it came, not the next step."""
        while (remaining := until - time.monotonic()) > 0:
            live = [i for i in self.rules.active if i not in self.dead]
            waitables = {self.processes[i].waitable: i for i in live}
            if None in waitables or not waitables:  # a transport without a waitable handle: poll
                time.sleep(min(remaining, 0.001))
                ready = live
            else:
                ready = [waitables[w] for w in multiprocessing.connection.wait(list(waitables), remaining)]
            for i in ready:
                if i not in self.dead:
                    self._drain(i)

    def _drain(self, i: int) -> bool:
        """Take every answer of layer i that is here; False if its process turned out dead."""
        try:
            while (reply := self._receive(i, 0.0)) is not None:
                self._take(i, reply)
        except LayerFault as e:
            self._fault(i, str(e))
            return False
        return True

    def _take(self, i: int, reply: Any) -> None:
        """A late answer, or one of a delayed layer: put it in its decision's place by the rules."""
        decision = self.asked.get((i, reply.episode, reply.step))
        if decision is None or decision.output is not None:
            return
        self._answer(decision, reply)
        if decision in self.pending[i] and self.rules.amend(i, decision.age, reply.output) == "late":
            decision.landed = self.t  # (not pending: its layer decided again before it came, so it is dropped)

    def _fault(self, i: int, message: str) -> None:
        """A layer's process died or stalled: stop it, then go on without it or stop, as the settings say."""
        self.dead.add(i)
        self.processes[i].abandon()  # (closing it would keep the clock waiting a third of a second for it to end)
        self.pending[i].clear()
        where = f"at step {self.t} of episode {self.episode}"
        if self.settings.on_fault == "stop":
            self.faults.append(f"{message} {where}; stopping (--on-fault stop)")
            self.notify(f"layered: {self.faults[-1]}")
            raise Stop(self.faults[-1])
        combiner = self.rules.layers[i].combiner
        if i == self.rules.active[-1]:  # the fastest present layer: its correction goes
            self.rules.held[i][...] = 0.0
            self.rules.inflight[i][...] = 0.0
            going_on = "going on with the slower layers' outputs alone"
        elif combiner is not None and combiner.encoding is not None:  # a gate: it defers to the layers below from now
            self.rules.held[i][..., -combiner.gate_dims:] = combiner.encoding.defer
            self.rules.inflight[i][..., -combiner.gate_dims:] = combiner.encoding.defer
            going_on = "going on with the layers below it, its gate deferring"
        else:
            going_on = "going on with its last output held"
        self.faults.append(f"{message} {where}; {going_on} (--on-fault hold)")
        self.notify(f"layered: {self.faults[-1]}")


def _never_executed(decisions: list[Decision]) -> None:
    """These late answers were replaced at the step they were put in place, before they were executed:
    they count as dropped, not as taking effect."""
    for decision in decisions:
        decision.landed = None
