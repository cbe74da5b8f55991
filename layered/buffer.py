"""A fixed-capacity replay buffer of layer transitions, stored as preallocated tensors on the
learner's device, so that minibatches are drawn where the networks are."""

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

    def __init__(self, obs_dim: int, action_dim: int, capacity: int, device: torch.device | str = "cpu") -> None:
        self.capacity = capacity
        self.size = 0
        self._next = 0
        self.device = torch.device(device)
        widths = {"obs": obs_dim, "action": action_dim, "reward": 1, "next_obs": obs_dim, "not_done": 1, "discount": 1}
        # empty, not zeros: rows are read only once written, and untouched pages of a large buffer
        # then take no memory
        self._store = {key: torch.empty((capacity, widths[key]), dtype=torch.float32, device=self.device)
                       for key in self.FIELDS}

    def add(self, t: Transition) -> None:
        """Store one transition."""
        row = {"obs": t.obs, "action": t.action, "reward": t.reward, "next_obs": t.next_obs,
               "not_done": 0.0 if t.terminated else 1.0, "discount": t.discount}
        for key, value in row.items():
            self._store[key][self._next] = torch.as_tensor(np.asarray(value, np.float32))
        self._next = (self._next + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """A uniform minibatch drawn with replacement (indices from `rng`, rows gathered on the device)."""
        idx = torch.from_numpy(rng.integers(0, self.size, size=batch_size)).to(self.device, non_blocking=True)
        return Batch(*(self._store[key][idx] for key in self.FIELDS))

    def __len__(self) -> int:
        return self.size

    def state_dict(self) -> dict[str, torch.Tensor | int]:
        """The stored transitions as tensors, for resuming a run."""
        stored = {key: self._store[key][: self.size].cpu().clone() for key in self.FIELDS}
        return {"size": self.size, "next": self._next, **stored}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned."""
        self.size, self._next = int(state["size"]), int(state["next"])
        for key in self.FIELDS:
            self._store[key][: self.size] = state[key].to(self.device)
