"""TempoRL (Biedenkapp et al., 2021) on TD3: a skip policy chooses for how many periods to hold an action.

The layer's output is TD3's action followed by a repeat count in 1..max_repeat (the layer's
`max_repeat`). A skip Q-network on (observation, action) values each count; it bootstraps from
the TD3 critic and learns from every partial repetition of each executed skip, while the TD3
part learns from every single period of it.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import torch
from gymnasium.spaces import Box
from pydantic import Field
from torch import nn

from layered.buffer import ReplayBuffer, Transition
from layered.learners.base import LEARNERS, Learner, UpdateStats
from layered.learners.td3 import TD3, TD3Config, adam, linear_macs, mlp


class TempoRLConfig(TD3Config):
    """TD3 settings plus the skip policy's exploration."""

    kind: Literal["temporl"] = "temporl"  # type: ignore[assignment]
    skip_epsilon: float = Field(0.1, ge=0, le=1)
    """While exploring, the probability of a uniformly random repeat count."""


@LEARNERS.register("temporl")
class TempoRL(Learner):
    """TD3 for the action, a skip Q-network for how long to hold it."""

    Config = TempoRLConfig
    config: TempoRLConfig

    def __init__(self, obs_space: Box, action_space: Box, config: TempoRLConfig, seed: int) -> None:
        super().__init__(obs_space, action_space, config, seed)
        if action_space.shape[0] < 2 or action_space.low[-1] != 1 or action_space.high[-1] < 2:
            raise ValueError("the temporl learner needs a layer with max_repeat > 1 (its last output is the count)")
        self.max_skip = int(action_space.high[-1])
        inner = Box(action_space.low[:-1], action_space.high[:-1], dtype=np.float32)
        self.td3 = TD3(obs_space, inner, TD3Config(**config.model_dump(exclude={"kind", "skip_epsilon"})), seed)
        self.rng = np.random.default_rng([seed, 1])
        obs_dim, act_dim = obs_space.shape[0], inner.shape[0]
        self.skip_q = mlp((obs_dim + act_dim, *config.hidden, self.max_skip))
        self.skip_opt = adam(self.skip_q.parameters(), config.lr)
        self.skip_buffer = ReplayBuffer(obs_dim, act_dim + 1, config.buffer_size)

    def random_action(self) -> np.ndarray:
        return np.append(self.td3.random_action(), self.rng.integers(1, self.max_skip + 1)).astype(np.float32)

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        action = self.td3.act(obs, explore)
        if explore and self.rng.random() < self.config.skip_epsilon:
            skip = int(self.rng.integers(1, self.max_skip + 1))
        else:
            x = torch.as_tensor(np.concatenate([obs, action]), dtype=torch.float32)
            skip = int(self.skip_q(x).argmax()) + 1
        return np.append(action, skip).astype(np.float32)

    def act_macs(self) -> int:
        return self.td3.act_macs() + linear_macs(self.skip_q)

    def observe(self, transition: Transition) -> None:
        """Store each period of the repeat for TD3 and every partial repetition for the skip Q."""
        action, gamma = transition.action[:-1], self.config.gamma
        if transition.path:
            states = [transition.obs, *(o for o, _ in transition.path)]
            rewards = [r for _, r in transition.path]
        else:
            states, rewards = [transition.obs, transition.next_obs], [transition.reward]
        n = len(rewards)
        for k in range(n):
            done = transition.terminated and k == n - 1
            self.td3.observe(Transition(states[k], action, rewards[k], states[k + 1], done, gamma))
        for start in range(n):
            total = 0.0
            for length in range(1, n - start + 1):
                total += gamma ** (length - 1) * rewards[start + length - 1]
                end = start + length
                self.skip_buffer.add(Transition(
                    states[start], np.append(action, length), total, states[end],
                    transition.terminated and end == n, gamma**length,
                ))

    def update(self) -> UpdateStats | None:
        stats = self.td3.update()
        if stats is None or len(self.skip_buffer) == 0:
            return stats
        b = self.skip_buffer.sample(self.config.batch_size, self.rng)
        action, length = b.action[:, :-1], b.action[:, -1:].long()
        with torch.no_grad():
            next_action = self.td3.actor_target(b.next_obs)
            q1, q2 = self.td3.critic_target(b.next_obs, next_action)
            target = b.reward + b.not_done * b.discount * torch.min(q1, q2)
        q = self.skip_q(torch.cat([b.obs, action], dim=-1)).gather(1, length - 1)
        loss = nn.functional.mse_loss(q, target)
        self.skip_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.skip_opt.step()
        return stats

    def state_dict(self) -> dict[str, Any]:
        return {
            "td3": self.td3.state_dict(), "skip_q": self.skip_q.state_dict(), "skip_opt": self.skip_opt.state_dict(),
        }

    def resume_state(self) -> dict[str, Any]:
        return {**super().resume_state(), "td3": self.td3.resume_state(), "skip_buffer": self.skip_buffer.state_dict()}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        super().load_resume_state(state)
        self.td3.load_resume_state(state["td3"])
        self.skip_buffer.load_state_dict(state["skip_buffer"])

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.td3.load_state_dict(state["td3"])
        self.skip_q.load_state_dict(state["skip_q"])
        self.skip_opt.load_state_dict(state["skip_opt"])


