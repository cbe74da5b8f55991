"""The learners that make a discrete choice on top of a TD3 action, for K seeds as one computation: the
jointly trained gate (`td3-gate`) and TempoRL (`temporl`).

Each seed's TD3 part is stacked as `TD3Group` stacks TD3, and its choice Q-network (`ChoiceQ`: the
gate's defer and commit, or TempoRL's repeat counts, valued for an observation and the action TD3
proposed there) is stacked beside it, with a replay tensor of its own and targets from the TD3
group's target critic. As with `TD3Group`, a seed's numbers do not depend on the other seeds', and
`seed_state_dict(k)` is seed k's state as a single learner's `state_dict`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from layered.buffer import Transition
from layered.learners.choice import ChoiceQ, TD3WithChoice
from layered.learners.gate_td3 import GateTD3
from layered.learners.stacked import StackedAdam, StackedMLP, StackedReplay
from layered.learners.td3 import TD3
from layered.learners.td3_group import DecisionPath, GroupLosses, TD3Group, pick, transition_rows
from layered.learners.temporl import TempoRL, skip_transitions


class ChoiceGroup:
    """K seeds' choice Q-networks stacked, each learning from its own choices' transitions."""

    def __init__(self, singles: Sequence[ChoiceQ], td3: TD3Group) -> None:
        first = singles[0]
        self.td3, self.n, self.head = td3, first.n, first.head
        self.net = StackedMLP([choice.net for choice in singles]).to(td3.device)
        self.opt = StackedAdam(list(self.net.parameters()), td3.config.lr, td3.k, first.opt.state_dict())
        # obs, action, choice, reward, next obs, not done, discount
        widths = (td3.obs_dim, td3.act_dim, 1, 1, td3.obs_dim, 1, 1)
        self.replay = StackedReplay(td3.k, td3.config.buffer_size, widths, td3.device, td3.captured)
        for k, choice in enumerate(singles):  # (a choice started from weights brings its moments, as TD3's do)
            self.opt.load_seed_state(k, choice.opt.state_dict())

    @torch.inference_mode()
    def choose(self, obs: np.ndarray, action: np.ndarray, epsilon: float, rng: np.random.Generator) -> np.ndarray:
        """Each seed's best-valued choice for each of its pairs of observation and action (`obs`, `action`:
        [K, n, ...] -> [K, n]), or with probability `epsilon` a uniformly random one."""
        x = self.td3.staging.put(np.concatenate([obs, action], axis=-1))
        best = self.net(x).argmax(dim=-1).cpu().numpy()
        if not epsilon:
            return best
        at_random = rng.random(best.shape) < epsilon
        return np.where(at_random, rng.integers(self.n, size=best.shape), best)

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
        seeds = self.td3.subset(rows)  # (the seeds that learn alone are computed)
        obs, action, choice, reward, next_obs, not_done, discount = (
            pick(t, seeds) for t in self.replay.sample(self.td3.config.batch_size, self.td3.torch_rng))
        with torch.no_grad():
            pair = torch.cat([next_obs, self.td3.actions(next_obs, self.td3.actor_target, seeds)], dim=-1)
            if self.head == "min":
                value = self.td3.critic_target(pair, seeds=seeds).amin(dim=1)
            else:
                value = self.td3.critic_target(pair, seeds=seeds, first=True)
            target = reward + not_done * discount * value
        chosen = self.net(torch.cat([obs, action], dim=-1), seeds=seeds).gather(-1, choice.long())
        losses = (chosen - target).square().mean(dim=(1, 2))
        self.opt.zero_grad()
        losses.sum().backward()
        self.opt.step(rows)

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's network and optimiser as a single `ChoiceQ`'s `state_dict` holds them."""
        return {"net": self.net.seed_state(k, ""), "opt": self.opt.seed_state(k)}

    def load_seed_state_dict(self, k: int, state: dict[str, Any]) -> None:
        self.net.load_seed_state(k, state["net"], "")
        self.opt.load_seed_state(k, state["opt"])

    def resume_state(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict()}  # (its replay: see `replays`)

    def load_resume_state(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])


class ChoiceLearnerGroup(ABC):
    """K learners of a `TD3WithChoice` kind, one per seed: TD3's action followed by the choice's output."""

    loss_names = TD3.loss_names

    def __init__(self, learners: Sequence[TD3WithChoice], seed: int = 0) -> None:
        first = learners[0]
        self.td3 = TD3Group([learner.td3 for learner in learners], seed)
        self.choice = ChoiceGroup([learner.choice for learner in learners], self.td3)
        self.epsilon = first.epsilon()
        self.values = np.array([first.encode(index) for index in range(self.choice.n)], np.float32)
        self.rng = np.random.default_rng([seed, 1])
        self.k = self.td3.k
        self.device = self.td3.device

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """[K, action + 1]: each seed's TD3 action and its choice (epsilon-greedy with `explore`)."""
        action = self.td3.act(obs, explore)
        choice = self.choice.choose(obs[:, None], action[:, None], self.epsilon if explore else 0.0, self.rng)[:, 0]
        return np.concatenate([action, self.values[choice][:, None]], axis=1)

    def greedy(self, obs: np.ndarray) -> np.ndarray:
        """[K, n, action + 1]: TD3's greedy actions for each seed's `n` observations ([K, n, obs]) and the best
        choices."""
        action = self.td3.greedy(obs)
        choice = self.choice.choose(obs, action, 0.0, self.rng)
        return np.concatenate([action, self.values[choice][..., None]], axis=-1)

    def random_action(self) -> np.ndarray:
        """[K, action + 1] warm-up outputs: TD3's warm-up actions and uniformly random choices."""
        choice = self.rng.integers(self.choice.n, size=self.k)
        return np.concatenate([self.td3.random_action(), self.values[choice][:, None]], axis=1)

    def act_macs(self) -> int:
        return self.td3.act_macs() + sum(w.shape[1] * w.shape[2] for w in self.choice.net.weights)

    @abstractmethod
    def observe(self, obs: np.ndarray, output: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None,
                paths: Sequence[DecisionPath] | None = None) -> None:
        """Store each seed's completed decision (in the seeds of the `rows` mask), as the single learner does."""

    def update(self, rows: np.ndarray | None = None) -> GroupLosses | None:
        """TD3's update of the seeds in `rows`, then their choices' (a choice learns when TD3 does)."""
        losses = self.td3.update(rows)
        if losses is not None:
            self.choice.update(losses["critic"][1])
        return losses

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's state as a single learner's `state_dict`."""
        return {"td3": self.td3.seed_state_dict(k), "choice": self.choice.seed_state_dict(k)}

    def load_seed_state_dict(self, k: int, state: dict[str, Any]) -> None:
        self.td3.load_seed_state_dict(k, state["td3"])
        self.choice.load_seed_state_dict(k, state["choice"])

    @property
    def replays(self) -> dict[str, StackedReplay]:
        """The replay buffers, which a group's checkpoint keeps apart from `resume_state` (layered.replay_journal)."""
        return {"td3": self.td3.replay, "choice": self.choice.replay}

    def resume_state(self) -> dict[str, Any]:
        return {"td3": self.td3.resume_state(), "choice": self.choice.resume_state(),
                "rng": self.rng.bit_generator.state}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        self.td3.load_resume_state(state["td3"])
        self.choice.load_resume_state(state["choice"])
        self.rng.bit_generator.state = state["rng"]


class GateTD3Group(ChoiceLearnerGroup):
    """K `GateTD3` learners: the choice is the gate's, 0 defers and 1 commits."""

    def __init__(self, learners: Sequence[GateTD3], seed: int = 0) -> None:
        super().__init__(learners, seed)
        assert learners[0].layout.gate is not None, "GateTD3.unfit refuses a layer without a gate"
        self.gate = learners[0].layout.gate

    def observe(self, obs: np.ndarray, output: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None,
                paths: Sequence[DecisionPath] | None = None) -> None:
        """Store each seed's transition for TD3 (the proposed action) and for the gate (its choice), as
        `GateTD3.observe` does for one."""
        action, commits = output[:, :-1], self.gate.commits(output[:, -1])
        self.td3.observe(obs, action, reward, next_obs, terminated, discount, rows)
        self.choice.add(obs, action, commits.astype(np.float32), reward, next_obs, terminated, discount, rows)


class TempoRLGroup(ChoiceLearnerGroup):
    """K `TempoRL` learners: the choice is the repeat count (k: k + 1 periods)."""

    def __init__(self, learners: Sequence[TempoRL], seed: int = 0) -> None:
        super().__init__(learners, seed)
        self.gamma = learners[0].config.gamma

    def observe(self, obs: np.ndarray, output: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None,
                paths: Sequence[DecisionPath] | None = None) -> None:
        """Store, per seed, each period of its repeat for TD3 and every partial repetition for the skip Q, as
        `TempoRL.observe` does for one (`skip_transitions`), the seeds' j-th transitions added together."""
        periods: list[list[Transition]] = [[] for _ in range(self.k)]
        skips: list[list[tuple[Transition, int]]] = [[] for _ in range(self.k)]
        for k in np.flatnonzero(np.ones(self.k, bool) if rows is None else rows).tolist():
            decision = Transition(obs[k], output[k], float(reward[k]), next_obs[k], bool(terminated[k]),
                                  float(discount[k]), tuple(paths[k]) if paths is not None else ())
            periods[k], skips[k] = skip_transitions(decision, self.gamma)
        for j in range(max(map(len, periods))):
            obs_j, action_j, reward_j, next_j, done_j, discount_j, present = _columns(
                [p[j] if j < len(p) else None for p in periods])
            self.td3.observe(obs_j, action_j, reward_j, next_j, done_j, discount_j, present)
        for j in range(max(map(len, skips))):
            chosen = [s[j] if j < len(s) else None for s in skips]
            obs_j, action_j, reward_j, next_j, done_j, discount_j, present = _columns([c and c[0] for c in chosen])
            choice = np.array([c[1] if c else 0 for c in chosen], np.float32)
            self.choice.add(obs_j, action_j, choice, reward_j, next_j, done_j, discount_j, present)


def _columns(transitions: Sequence[Transition | None]) -> tuple[np.ndarray, ...]:
    """One transition per seed (None: none for that seed) as the [K, ...] arrays a group stores, and the
    mask of the seeds that have one."""
    present = np.array([t is not None for t in transitions])
    first = next(t for t in transitions if t is not None)
    filled = [t if t is not None else first for t in transitions]  # (rows outside the mask are not stored)
    return (np.stack([t.obs for t in filled]), np.stack([t.action for t in filled]),
            np.array([t.reward for t in filled]), np.stack([t.next_obs for t in filled]),
            np.array([t.terminated for t in filled]), np.array([t.discount for t in filled]), present)
