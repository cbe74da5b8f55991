"""The jointly trained gate's learner (`td3-gate`) for K seeds as one computation.

Each seed's TD3 part is stacked as `TD3Group` stacks TD3, and its gate Q-network (`ChoiceQ`: values of
defer and commit for an observation and the action TD3 proposed there) is stacked beside it, with a
replay tensor of its own and targets from the TD3 group's target critic. As with `TD3Group`, a seed's
numbers do not depend on the other seeds', and `seed_state_dict(k)` is seed k's state as a single
`GateTD3` learner's `state_dict`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from layered.learners.choice import ChoiceQ
from layered.learners.gate_td3 import GateTD3
from layered.learners.stacked import StackedAdam, StackedMLP, StackedReplay, masked
from layered.learners.td3 import TD3
from layered.learners.td3_group import GroupLosses, TD3Group, transition_rows


class ChoiceGroup:
    """K seeds' choice Q-networks stacked, each learning from its own choices' transitions."""

    def __init__(self, singles: Sequence[ChoiceQ], td3: TD3Group) -> None:
        first = singles[0]
        self.td3, self.n, self.head = td3, first.n, first.head
        self.net = StackedMLP([choice.net for choice in singles]).to(td3.device)
        self.opt = StackedAdam(list(self.net.parameters()), td3.config.lr, td3.k, first.opt.state_dict())
        # obs, action, choice, reward, next obs, not done, discount
        widths = (td3.obs_dim, td3.act_dim, 1, 1, td3.obs_dim, 1, 1)
        self.replay = StackedReplay(td3.k, td3.config.buffer_size, widths, td3.device)

    @torch.inference_mode()
    def choose(self, obs: np.ndarray, action: np.ndarray, epsilon: float, rng: np.random.Generator) -> np.ndarray:
        """[K] each seed's best-valued choice, or with probability `epsilon` a uniformly random one."""
        x = torch.as_tensor(np.concatenate([obs, action], axis=1, dtype=np.float32), device=self.td3.device)
        best = self.net(x[:, None])[:, 0].argmax(dim=-1).cpu().numpy()
        if not epsilon:
            return best
        at_random = rng.random(len(best)) < epsilon
        return np.where(at_random, rng.integers(self.n, size=len(best)), best)

    def add(self, obs: np.ndarray, action: np.ndarray, choice: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None) -> None:
        """Store, per seed of the `rows` mask, that `choice` was made with `action` in this transition."""
        data = transition_rows(obs, action, reward, next_obs, terminated, discount)
        self.replay.add(np.insert(data, obs.shape[1] + action.shape[1], choice, axis=1), rows)

    def update(self, rows: np.ndarray) -> None:
        """One regression of the seeds in `rows` (those with a stored choice) of their chosen values on reward
        + discount x their TD3 target's value, as `ChoiceQ.update` does for one."""
        rows = rows & (self.replay.stored > 0)
        if not rows.any():
            return
        obs, action, choice, reward, next_obs, not_done, discount = self.replay.sample(
            self.td3.config.batch_size, self.td3.torch_rng)
        with torch.no_grad():
            pair = torch.cat([next_obs, self.td3.actions(next_obs, self.td3.actor_target)], dim=-1)
            value = self.td3.q1_target(pair)
            if self.head == "min":
                value = torch.min(value, self.td3.q2_target(pair))
            target = reward + not_done * discount * value
        chosen = self.net(torch.cat([obs, action], dim=-1)).gather(-1, choice.long())
        losses = (chosen - target).square().mean(dim=(1, 2))
        self.opt.zero_grad()
        losses.sum().backward()
        self.opt.step(masked(rows, self.td3.device))

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's network and optimiser as a single `ChoiceQ`'s `state_dict` holds them."""
        return {"net": self.net.seed_state(k, ""), "opt": self.opt.seed_state(k)}

    def load_seed_state_dict(self, k: int, state: dict[str, Any]) -> None:
        self.net.load_seed_state(k, state["net"], "")
        self.opt.load_seed_state(k, state["opt"])

    def resume_state(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict(), "replay": self.replay.state_dict()}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])
        self.replay.load_state_dict(state["replay"])


class GateTD3Group:
    """K `GateTD3` learners of one configuration, one per seed, acting and updating together."""

    loss_names = TD3.loss_names

    def __init__(self, learners: Sequence[GateTD3], seed: int = 0) -> None:
        first = learners[0]
        assert first.layout.gate is not None, "GateTD3.unfit refuses a layer without a gate"
        self.gate = first.layout.gate
        self.td3 = TD3Group([learner.td3 for learner in learners], seed)
        self.choice = ChoiceGroup([learner.choice for learner in learners], self.td3)
        self.epsilon = first.epsilon()
        self.values = np.array([self.gate.value(commit=False), self.gate.value(commit=True)], np.float32)
        self.rng = np.random.default_rng([seed, 1])
        self.k = self.td3.k

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """[K, action + 1]: each seed's TD3 action and its gate's choice (epsilon-greedy with `explore`)."""
        action = self.td3.act(obs, explore)
        choice = self.choice.choose(obs, action, self.epsilon if explore else 0.0, self.rng)
        return np.concatenate([action, self.values[choice][:, None]], axis=1)

    def random_action(self) -> np.ndarray:
        """[K, action + 1] warm-up outputs: TD3's warm-up actions and uniformly random gate choices."""
        choice = self.rng.integers(2, size=self.k)
        return np.concatenate([self.td3.random_action(), self.values[choice][:, None]], axis=1)

    def act_macs(self) -> int:
        return self.td3.act_macs() + sum(w.shape[1] * w.shape[2] for w in self.choice.net.weights)

    def observe(self, obs: np.ndarray, output: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Store each seed's transition for TD3 (the proposed action) and for the gate (its choice), as
        `GateTD3.observe` does for one."""
        action, commits = output[:, :-1], self.gate.commits(output[:, -1])
        self.td3.observe(obs, action, reward, next_obs, terminated, discount, rows)
        self.choice.add(obs, action, commits.astype(np.float32), reward, next_obs, terminated, discount, rows)

    def update(self, rows: np.ndarray | None = None) -> GroupLosses | None:
        """TD3's update of the seeds in `rows`, then their gates' (the gate learns when TD3 does)."""
        losses = self.td3.update(rows)
        if losses is not None:
            self.choice.update(losses["critic"][1])
        return losses

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's state as a single `GateTD3` learner's `state_dict`."""
        return {"td3": self.td3.seed_state_dict(k), "choice": self.choice.seed_state_dict(k)}

    def load_seed_state_dict(self, k: int, state: dict[str, Any]) -> None:
        self.td3.load_seed_state_dict(k, state["td3"])
        self.choice.load_seed_state_dict(k, state["choice"])

    def resume_state(self) -> dict[str, Any]:
        return {"td3": self.td3.resume_state(), "choice": self.choice.resume_state(),
                "rng": self.rng.bit_generator.state}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        self.td3.load_resume_state(state["td3"])
        self.choice.load_resume_state(state["choice"])
        self.rng.bit_generator.state = state["rng"]
