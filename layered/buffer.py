"""A fixed-capacity replay buffer of layer transitions, stored as preallocated numpy arrays."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch


class Transition(NamedTuple):
    """One decision of a layer: what it saw and did, and what followed until its next decision."""

    obs: np.ndarray
    action: np.ndarray
    reward: float
    next_obs: np.ndarray
    terminated: bool
    discount: float  # the discount applied to the bootstrap value (gamma, or gamma**k)
    path: tuple[tuple[np.ndarray, float], ...] = ()  # (observation, reward) per period of a repeat


class Batch(NamedTuple):
    """A sampled minibatch as float32 tensors; `not_done` is 0 where the episode terminated."""

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    not_done: torch.Tensor
    discount: torch.Tensor


class ReplayBuffer:
    """Ring buffer that overwrites its oldest transitions once full."""

    FIELDS = ("obs", "action", "reward", "next_obs", "not_done", "discount")

    def __init__(self, obs_dim: int, action_dim: int, capacity: int) -> None:
        self.capacity = capacity
        self.size = 0
        self._next = 0
        self._obs = np.zeros((capacity, obs_dim), np.float32)
        self._action = np.zeros((capacity, action_dim), np.float32)
        self._reward = np.zeros((capacity, 1), np.float32)
        self._next_obs = np.zeros((capacity, obs_dim), np.float32)
        self._not_done = np.zeros((capacity, 1), np.float32)
        self._discount = np.zeros((capacity, 1), np.float32)

    def add(self, t: Transition) -> None:
        """Store one transition."""
        i = self._next
        self._obs[i] = t.obs
        self._action[i] = t.action
        self._reward[i] = t.reward
        self._next_obs[i] = t.next_obs
        self._not_done[i] = 0.0 if t.terminated else 1.0
        self._discount[i] = t.discount
        self._next = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """A uniform minibatch drawn with replacement."""
        idx = rng.integers(0, self.size, size=batch_size)
        arrays = (self._obs, self._action, self._reward, self._next_obs, self._not_done, self._discount)
        return Batch(*(torch.from_numpy(a[idx]) for a in arrays))

    def __len__(self) -> int:
        return self.size

    def state_dict(self) -> dict[str, torch.Tensor | int]:
        """The stored transitions as tensors, for resuming a run."""
        stored = {key: torch.from_numpy(getattr(self, f"_{key}")[: self.size].copy()) for key in self.FIELDS}
        return {"size": self.size, "next": self._next, **stored}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned."""
        self.size, self._next = int(state["size"]), int(state["next"])
        for key in self.FIELDS:
            getattr(self, f"_{key}")[: self.size] = state[key].numpy()
