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
    path: tuple[tuple[np.ndarray, float, int], ...] = ()  # per period of a repeat: observation, reward, discount units


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
        widths = (obs_dim, action_dim, 1, obs_dim, 1, 1)
        ends = np.cumsum(widths).tolist()
        self._columns = {key: slice(end - width, end)
                         for key, width, end in zip(self.FIELDS, widths, ends, strict=True)}
        # One row per transition, so that storing one is one copy and a minibatch one gather; empty,
        # not zeros: rows are read only once written, and untouched pages then take no memory.
        self._rows = torch.empty((capacity, ends[-1]), dtype=torch.float32, device=self.device)

    def add(self, t: Transition) -> None:
        """Store one transition."""
        row = np.concatenate([np.ravel(t.obs), np.ravel(t.action), [t.reward], np.ravel(t.next_obs),
                              [0.0 if t.terminated else 1.0, t.discount]], dtype=np.float32)
        self._rows[self._next] = torch.from_numpy(row)
        self._next = (self._next + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """A uniform minibatch drawn with replacement (indices from `rng`, rows gathered on the device)."""
        idx = torch.from_numpy(rng.integers(0, self.size, size=batch_size)).to(self.device, non_blocking=True)
        rows = self._rows[idx]
        return Batch(*(rows[:, self._columns[key]] for key in self.FIELDS))

    def __len__(self) -> int:
        return self.size

    def state_dict(self) -> dict[str, torch.Tensor | int]:
        """The stored transitions, a tensor per field, for resuming a run."""
        stored = {key: self._rows[: self.size, self._columns[key]].cpu().clone() for key in self.FIELDS}
        return {"size": self.size, "next": self._next, **stored}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned."""
        self.size, self._next = int(state["size"]), int(state["next"])
        for key in self.FIELDS:
            self._rows[: self.size, self._columns[key]] = state[key].to(self.device)
