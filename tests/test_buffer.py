"""The replay buffer: what is stored is what is sampled, field by field, and it survives a state round trip."""

import numpy as np
import pytest
import torch

from layered.buffer import ReplayBuffer, Transition

A = Transition(obs=np.array([1.0, 2.0]), action=np.array([0.5]), reward=-3.0, next_obs=np.array([4.0, 5.0]),
               terminated=True, discount=0.99)
B = Transition(obs=np.array([6.0, 7.0]), action=np.array([-0.25]), reward=2.5, next_obs=np.array([8.0, 9.0]),
               terminated=False, discount=0.9801)


def test_a_sampled_minibatch_holds_the_stored_fields_of_the_drawn_rows():
    buffer = ReplayBuffer(obs_dim=2, action_dim=1, capacity=4)
    buffer.add(A)
    buffer.add(B)
    idx = np.random.default_rng(3).integers(0, 2, size=5)
    batch = buffer.sample(5, np.random.default_rng(3))
    for k, i in enumerate(idx):
        t = (A, B)[i]
        assert batch.obs[k].tolist() == t.obs.tolist() and batch.next_obs[k].tolist() == t.next_obs.tolist()
        assert batch.action[k].tolist() == t.action.tolist()
        assert batch.reward[k].item() == t.reward
        assert batch.not_done[k].item() == (0.0 if t.terminated else 1.0)
        assert batch.discount[k].item() == np.float32(t.discount)
    assert [f.shape for f in batch] == [(5, 2), (5, 1), (5, 1), (5, 2), (5, 1), (5, 1)]


def test_a_full_buffer_overwrites_its_oldest_row():
    buffer = ReplayBuffer(obs_dim=2, action_dim=1, capacity=2)
    for t in (A, B, B):
        buffer.add(t)
    assert len(buffer) == 2
    assert buffer.fields()["obs"].tolist() == [[6.0, 7.0], [6.0, 7.0]]
    assert buffer.stored.tolist() == [3]


@pytest.mark.parametrize("capacity", [8, 2])  # the ring never wraps / wraps
def test_a_buffer_refilled_from_its_new_rows_gives_the_same_minibatches(capacity):
    buffer, copy = ReplayBuffer(2, 1, capacity=capacity), ReplayBuffer(2, 1, capacity=capacity)
    segments = []
    for t in (A, B, A):
        since = buffer.stored.copy()
        buffer.add(t)
        rows, first = buffer.rows_since(since)
        segments.append((rows, first, buffer.stored - first))
    assert [s[0][:, 3].tolist() for s in segments] == [[-3.0], [2.5], [-3.0]]  # each step's new row, its reward
    copy.restore(buffer.stored, segments)
    assert (copy.size, copy._next) == (buffer.size, buffer._next)
    one, other = buffer.sample(16, np.random.default_rng(0)), copy.sample(16, np.random.default_rng(0))
    assert all(torch.equal(x, y) for x, y in zip(one, other, strict=True))


def test_a_buffer_saved_by_layered_0_1_0_is_restored_with_its_count():
    """Such a checkpoint held the buffer's fields with its size and next slot; the count of rows stored in all is
    what the ring's slots say (a wrapped ring: one round plus the next slot)."""
    for capacity, size, next_, stored in ((8, 3, 3, 3), (2, 2, 1, 3)):
        source = ReplayBuffer(2, 1, capacity=capacity)
        for t in (A, B, A)[:stored]:
            source.add(t)
        old = {"size": size, "next": next_, **source.fields()}
        buffer = ReplayBuffer(2, 1, capacity=capacity)
        buffer.load_fields(old)
        assert buffer.stored.tolist() == [stored] and torch.equal(buffer._rows[:size], source._rows[:size])
