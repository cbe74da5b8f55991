"""TempoRL (Biedenkapp et al., 2021) on TD3: a skip policy chooses for how many periods to hold an action.

The layer's output is TD3's action followed by a repeat count in 1..max_repeat (the layer's
`max_repeat`). A skip Q-network on (observation, action) values each count; it bootstraps from
the TD3 critic and learns from every partial repetition of each executed skip, while the TD3
part learns from every single period of it.
"""

from __future__ import annotations

from typing import Literal

from gymnasium.spaces import Box
from pydantic import Field

from layered.buffer import Transition
from layered.learners.choice import TD3WithChoice
from layered.learners.td3 import TD3Config
from layered.outputs import OutputLayout


class TempoRLConfig(TD3Config):
    """TD3 settings plus the skip policy's exploration."""

    kind: Literal["temporl"] = "temporl"  # type: ignore[assignment]
    skip_epsilon: float = Field(default=0.1, ge=0, le=1)
    """While exploring, the probability of a uniformly random repeat count."""


class TempoRL(TD3WithChoice):
    """TD3 for the action, a skip Q-network for how long to hold it (choice k: k + 1 periods)."""

    Config = TempoRLConfig
    config: TempoRLConfig

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: TempoRLConfig,
                 seed: int) -> None:
        super().__init__(obs_space, action_space, layout, config, seed, choices=layout.max_repeat)

    @classmethod
    def unfit(cls, layout: OutputLayout) -> str | None:
        if not layout.repeats or layout.gate_dims:
            return "it needs a layer with max_repeat > 1 and no gate (its last output is the repeat count)"
        return None

    def encode(self, index: int) -> float:
        return float(index + 1)

    def epsilon(self) -> float:
        return self.config.skip_epsilon

    def observe(self, transition: Transition) -> None:
        """Store each period of the repeat for TD3 and every partial repetition for the skip Q (see
        `skip_transitions`)."""
        periods, skips = skip_transitions(transition, self.config.gamma)
        for period in periods:
            self.td3.observe(period)
        for skip, choice in skips:
            self.choice.add(skip, choice)


def skip_transitions(transition: Transition, gamma: float) -> tuple[list[Transition], list[tuple[Transition, int]]]:
    """A TempoRL decision's transitions: one per period of the repeat, for TD3 (the action without its
    repeat count), and one per partial repetition, for the skip Q, with its choice (k: k + 1 periods).

    A span of periods is discounted by gamma to the power of the discount units the stack gave them
    (one per period, or one per base step with train.discount = "step"); a decision without a path
    spans one period, with the transition's own discount."""
    action = transition.action[:-1]
    if transition.path:
        states = [transition.obs, *(o for o, _, _ in transition.path)]
        rewards = [r for _, r, _ in transition.path]
        units = [u for _, _, u in transition.path]
    else:
        states, rewards, units = [transition.obs, transition.next_obs], [transition.reward], []
    n = len(rewards)

    def discount(start: int, end: int) -> float:
        return gamma ** sum(units[start:end]) if units else transition.discount

    periods = [Transition(states[k], action, rewards[k], states[k + 1], transition.terminated and k == n - 1,
                          discount(k, k + 1)) for k in range(n)]
    skips = []
    for start in range(n):
        total, weight = 0.0, 1.0
        for length in range(1, n - start + 1):
            total += weight * rewards[start + length - 1]
            end = start + length
            weight = discount(start, end)
            done = transition.terminated and end == n
            skips.append((Transition(states[start], action, total, states[end], done, weight), length - 1))
    return periods, skips
