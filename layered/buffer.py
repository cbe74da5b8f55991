"""A fixed-capacity replay buffer of layer transitions, stored as preallocated tensors on the
learner's device, so that minibatches are drawn where the networks are."""

from __future__ import annotations

from collections.abc import Iterable
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


def rows_since(rows: torch.Tensor, stored: np.ndarray, since: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
    """Of K ring buffers, `rows` ([K, capacity, width]), which stored `stored[k]` rows each: the rows each stored
    after its first `since[k]` that its ring still holds, buffer after buffer in the order stored, on the CPU; and
    the index among its stored rows of each buffer's first one. What a checkpoint writes of a replay buffer
    (layered.replay_journal): only what is new."""
    first = np.maximum(since, stored - rows.shape[1])
    buffers, index = _indices(first, stored - first)
    slots = torch.from_numpy(index % rows.shape[1]).to(rows.device)
    return rows[torch.from_numpy(buffers).to(rows.device), slots].cpu(), first


def put_rows(rows: torch.Tensor, stored: np.ndarray, segments: Iterable[tuple[torch.Tensor, np.ndarray, np.ndarray]]
             ) -> None:
    """Refill K ring buffers, `rows`, to hold their last `stored[k]` rows from `rows_since`'s outputs, each as (rows,
    first, counts per buffer), in the order they were taken; a row its ring has since overwritten is left out
    (as is one a smaller ring cannot hold)."""
    capacity = rows.shape[1]
    for data, first, counts in segments:
        buffers, index = _indices(first, counts)
        kept = index >= np.repeat(stored - capacity, counts)
        rows[torch.from_numpy(buffers[kept]).to(rows.device), torch.from_numpy(index[kept] % capacity).to(rows.device)
             ] = data[torch.from_numpy(kept)].to(rows.device)


def _indices(first: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Buffer k's stored rows `first[k]` to `first[k] + counts[k]`, buffer after buffer: each one's buffer and index."""
    offsets = np.cumsum(counts) - counts  # where each buffer's rows start in the list
    index = np.arange(int(counts.sum())) + np.repeat(first - offsets, counts)
    return np.repeat(np.arange(len(counts)), counts), index


class ReplayBuffer:
    """Ring buffer that overwrites its oldest transitions once full."""

    k = 1  # (one buffer: what layered.replay_journal keeps of K of them)

    FIELDS = ("obs", "action", "reward", "next_obs", "not_done", "discount")

    def __init__(self, obs_dim: int, action_dim: int, capacity: int, device: torch.device | str = "cpu") -> None:
        self.capacity = capacity
        self._added = 0  # transitions added in all: the slot of the next, and how many the ring holds, follow
        self.device = torch.device(device)
        widths = (obs_dim, action_dim, 1, obs_dim, 1, 1)
        ends = np.cumsum(widths).tolist()
        self._columns = {key: slice(end - width, end)
                         for key, width, end in zip(self.FIELDS, widths, ends, strict=True)}
        # One row per transition, so that storing one is one copy and a minibatch one gather; empty,
        # not zeros: rows are read only once written, and untouched pages then take no memory.
        self._rows = torch.empty((capacity, ends[-1]), dtype=torch.float32, device=self.device)

    def keep_on_host(self) -> None:
        """Hold the rows in host memory, untouched: for a buffer that another stands in for (a learner trained
        through a group of one), which then takes no device memory, nor host memory until written."""
        self.device = torch.device("cpu")
        self._rows = torch.empty(self._rows.shape, dtype=self._rows.dtype)

    @property
    def stored(self) -> np.ndarray:
        """Transitions added in all, as the one count of `layered.replay_journal`'s K."""
        return np.array([self._added], np.int64)

    @property
    def size(self) -> int:
        """Transitions the ring holds."""
        return min(self._added, self.capacity)

    @property
    def _next(self) -> int:
        """The slot the next transition is stored in."""
        return self._added % self.capacity

    def add(self, t: Transition) -> None:
        """Store one transition."""
        row = np.concatenate([np.ravel(t.obs), np.ravel(t.action), [t.reward], np.ravel(t.next_obs),
                              [0.0 if t.terminated else 1.0, t.discount]], dtype=np.float32)
        self._rows[self._next] = torch.from_numpy(row)
        self._added += 1

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """A uniform minibatch drawn with replacement (indices from `rng`, rows gathered on the device)."""
        idx = torch.from_numpy(rng.integers(0, self.size, size=batch_size)).to(self.device, non_blocking=True)
        rows = self._rows[idx]
        return Batch(*(rows[:, self._columns[key]] for key in self.FIELDS))

    def __len__(self) -> int:
        return self.size

    def fields(self) -> dict[str, torch.Tensor]:
        """The stored transitions, a tensor per field, in the order of their slots."""
        return {key: self._rows[: self.size, self._columns[key]].cpu().clone() for key in self.FIELDS}

    def rows_since(self, since: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
        """`rows_since` of this one buffer: the rows stored after the first `since[0]`."""
        return rows_since(self._rows[None], self.stored, since)

    def restore(self, stored: np.ndarray, segments: Iterable[tuple[torch.Tensor, np.ndarray, np.ndarray]]) -> None:
        """Refill the buffer from `rows_since`'s outputs (see `put_rows`) and set its counts to `stored[0]`."""
        put_rows(self._rows[None], stored, segments)
        self._added = int(stored[0])

    def load_fields(self, state: dict[str, Any]) -> None:
        """Restore a buffer as a checkpoint of layered 0.1.0 holds it (its fields, size and next slot)."""
        size, next_slot = int(state["size"]), int(state["next"])
        for key in self.FIELDS:
            self._rows[:size, self._columns[key]] = state[key].to(self.device)
        self._added = size if size < self.capacity else self.capacity + next_slot  # (a full ring: one round on)
