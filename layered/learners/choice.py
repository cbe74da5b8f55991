"""A discrete choice made on top of a TD3 action: a Q-network on (observation, action) whose
targets bootstrap from the TD3 critic. TempoRL's skip length and a learned gate are such choices."""

from __future__ import annotations

import copy
from abc import abstractmethod
from typing import Any, Literal

import numpy as np
import torch
from gymnasium.spaces import Box
from torch import nn

from layered.buffer import ReplayBuffer, Transition
from layered.learners.base import Learner, Losses
from layered.learners.adam import Adam
from layered.learners.td3 import TD3, TD3Config, linear_macs, mlp
from layered.outputs import OutputLayout


class ChoiceQ:
    """Values `n` choices for a state and the action TD3 proposed there, and learns them."""

    def __init__(self, td3: TD3, n: int, head: Literal["min", "q1"] = "min") -> None:
        cfg = td3.config
        obs_dim, act_dim = td3.obs_space.shape[0], td3.action_space.shape[0]
        self.td3 = td3
        self.n = n
        self.head = head
        self.net = mlp((obs_dim + act_dim, *cfg.hidden, n)).to(td3.device)
        self.opt = Adam(self.net.parameters(), cfg.lr)
        self.buffer = ReplayBuffer(obs_dim, act_dim + 1, cfg.buffer_size, td3.device)  # the choice is the last column

    @torch.no_grad()
    def choose(self, obs: np.ndarray, action: np.ndarray, epsilon: float, rng: np.random.Generator) -> int:
        """The index of the best choice, or with probability `epsilon` a uniformly random one."""
        if epsilon and rng.random() < epsilon:
            return int(rng.integers(self.n))
        x = torch.as_tensor(np.concatenate([obs, action]), dtype=torch.float32, device=self.td3.device)
        return int(self.net(x).argmax())

    @torch.no_grad()
    def best(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """The best choice's index for each row of a batch (`obs`: [n, obs], `action`: [n, action] -> [n])."""
        x = torch.as_tensor(np.concatenate([obs, action], axis=1), dtype=torch.float32, device=self.td3.device)
        return self.net(x).argmax(dim=1).cpu().numpy()

    def add(self, transition: Transition, choice: int) -> None:
        """Store that `choice` was made with `transition.action` (without the choice's own output)."""
        self.buffer.add(transition._replace(action=np.append(transition.action, choice), path=()))

    def update(self, batch_size: int, rng: np.random.Generator) -> None:
        """One regression of the chosen values on reward + discount x the TD3 target's value."""
        if len(self.buffer) == 0:
            return
        b = self.buffer.sample(batch_size, rng)
        action, choice = b.action[:, :-1], b.action[:, -1:].long()
        target = b.reward + b.not_done * b.discount * self.bootstrap(b.next_obs)
        loss = nn.functional.mse_loss(self.net(torch.cat([b.obs, action], dim=-1)).gather(1, choice), target)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()

    @torch.no_grad()
    def bootstrap(self, next_obs: torch.Tensor) -> torch.Tensor:
        """TD3's target critic on the target actor's action: the smaller head, or the first (`head`)."""
        q1, q2 = self.td3.critic_target(next_obs, self.td3.actor_target(next_obs))
        return q1 if self.head == "q1" else torch.min(q1, q2)

    def macs(self) -> int:
        """Multiply-accumulates of one forward pass of the choice network."""
        return linear_macs(self.net)

    def state_dict(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])


class ActionAndChoice(nn.Module):
    """TD3's action for one observation followed by the output value of the best-valued choice."""

    values: torch.Tensor

    def __init__(self, actor: nn.Module, choice: nn.Module, values: list[float]) -> None:
        super().__init__()
        self.actor = actor
        self.choice = choice
        self.register_buffer("values", torch.tensor(values, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        action = self.actor(obs)
        best = self.choice(torch.cat([obs, action], dim=-1)).argmax(dim=-1, keepdim=True)
        return torch.cat([action, self.values[best]], dim=-1)


class TD3WithChoice(Learner):
    """A learner whose output is a TD3 action followed by one discrete choice, encoded as a number."""

    loss_names = TD3.loss_names

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: TD3Config, seed: int,
                 choices: int, head: Literal["min", "q1"] = "min") -> None:
        super().__init__(obs_space, action_space, layout, config, seed)
        inner = Box(action_space.low[:-1], action_space.high[:-1], dtype=np.float32)  # the choice is the last entry
        own = set(type(config).model_fields) - set(TD3Config.model_fields)
        td3_config = TD3Config(**config.model_dump(exclude={"kind", *own}))
        self.td3 = TD3(obs_space, inner, OutputLayout(layout.size - 1), td3_config, seed)
        self.rng = np.random.default_rng([seed, 1])
        self.choice = ChoiceQ(self.td3, choices, head)
        self.device = self.td3.device

    @abstractmethod
    def encode(self, index: int) -> float:
        """The output value of choice `index`."""

    @abstractmethod
    def epsilon(self) -> float:
        """While exploring, the probability of a uniformly random choice."""

    def random_action(self) -> np.ndarray:
        choice = self.encode(int(self.rng.integers(self.choice.n)))
        return np.append(self.td3.random_action(), choice).astype(np.float32)

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        action = self.td3.act(obs, explore)
        index = self.choice.choose(obs, action, self.epsilon() if explore else 0.0, self.rng)
        return np.append(action, self.encode(index)).astype(np.float32)

    def greedy(self, obs: np.ndarray) -> np.ndarray:
        action = self.td3.greedy(obs)
        values = np.array([self.encode(index) for index in range(self.choice.n)], np.float32)
        return np.concatenate([action, values[self.choice.best(obs, action)][:, None]], axis=1)

    def policy(self) -> nn.Module:
        values = [self.encode(k) for k in range(self.choice.n)]
        choice = copy.deepcopy(self.choice.net).cpu().eval().requires_grad_(False)
        return ActionAndChoice(self.td3.policy(), choice, values)

    def act_macs(self) -> int:
        return self.td3.act_macs() + self.choice.macs()

    def computes_in(self) -> str:
        return self.td3.computes_in()

    def update(self) -> Losses | None:
        losses = self.td3.update()
        if losses is not None:
            self.choice.update(self.td3.config.batch_size, self.rng)
        return losses

    def state_dict(self) -> dict[str, Any]:
        return {"td3": self.td3.state_dict(), "choice": self.choice.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.td3.load_state_dict(state["td3"])
        self.choice.load_state_dict(state["choice"])

    @property
    def replays(self) -> dict[str, ReplayBuffer]:
        return {"td3": self.td3.buffer, "choice": self.choice.buffer}

    def resume_state(self) -> dict[str, Any]:
        return {**super().resume_state(), "td3": self.td3.resume_state()}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        super().load_resume_state(state)
        self.td3.load_resume_state(state["td3"])
        if "choices" in state:  # a checkpoint of layered 0.1.0, which held the buffer
            self.choice.buffer.load_fields(state["choices"])
