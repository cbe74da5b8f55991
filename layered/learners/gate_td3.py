"""A gate layer's learner for jointly trained gated stacks (the authors' later TLA).

TD3 proposes the layer's action; a gate Q-network on (observation, proposed action) values the
two choices, defer (let the layers below act) or commit (hold the action for the period), and
picks between them epsilon-greedily while exploring. The gate's target bootstraps from TD3's
target critic, so both learn from the same transitions of the layer.
"""

from __future__ import annotations

from typing import Literal

from gymnasium.spaces import Box
from pydantic import Field

from layered.buffer import Transition
from layered.learners.choice import TD3WithChoice
from layered.learners.td3 import TD3Config
from layered.outputs import OutputLayout


class GateTD3Config(TD3Config):
    """TD3 settings plus the gate's exploration."""

    kind: Literal["td3-gate"] = "td3-gate"  # type: ignore[assignment]
    gate_epsilon: float = Field(default=0.1, ge=0, le=1)
    """While exploring, the probability of a uniformly random gate choice."""
    gate_target: Literal["min", "q1"] = "min"
    """The gate bootstraps from TD3's target critic: the smaller of its two heads, as TD3's own
    target does, or the first head alone, as the authors' code does."""


class GateTD3(TD3WithChoice):
    """TD3 for the proposed action, a two-valued Q-network for the gate (choice 0 defers, 1 commits)."""

    Config = GateTD3Config
    config: GateTD3Config

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: GateTD3Config,
                 seed: int) -> None:
        super().__init__(obs_space, action_space, layout, config, seed, choices=2, head=config.gate_target)

    @classmethod
    def unfit(cls, layout: OutputLayout) -> str | None:
        if layout.gate is None or layout.gate_dims != 1 or layout.repeats:
            return "it needs a gate layer (combine = 'gate', above another layer) that does not repeat"
        return None

    def encode(self, index: int) -> float:
        assert self.layout.gate is not None, "unfit refuses a layer without a gate"
        return self.layout.gate.value(commit=index == 1)

    def epsilon(self) -> float:
        return self.config.gate_epsilon

    def observe(self, transition: Transition) -> None:
        proposed = transition._replace(action=transition.action[:-1], path=())
        self.td3.observe(proposed)
        assert self.layout.gate is not None, "unfit refuses a layer without a gate"
        self.choice.add(proposed, 1 if self.layout.gate.commits(transition.action[-1]) else 0)
