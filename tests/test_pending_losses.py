"""The losses kept on the device until the loop reads them back: every update's, in order, by name, copied."""

import numpy as np
import torch

from layered.pending_losses import PendingLosses


def test_every_update_comes_back_in_order_with_its_names_and_note_past_the_buffers_first_size():
    pending = PendingLosses()
    for u in range(150):  # the buffer starts at 64 rows: it doubles twice
        losses = {"critic": torch.tensor(float(u))}
        if u % 2:
            losses["actor"] = torch.tensor(-float(u))
        pending.add(losses, note=u)
    assert len(pending) == 150
    updates = pending.read()
    assert [note for _, note in updates] == list(range(150))
    for u, (losses, _) in enumerate(updates):
        assert list(losses) == (["critic", "actor"] if u % 2 else ["critic"])
        assert losses["critic"] == u and losses.get("actor", -u) == -u
    assert len(pending) == 0 and pending.read() == []


def test_a_groups_losses_per_seed_and_their_masks():
    pending = PendingLosses()
    took = np.array([True, False, True])
    pending.add({"critic": torch.tensor([1.0, 2.0, 3.0]), "actor": torch.tensor([4.0, 5.0, 6.0])}, {"critic": took})
    pending.add({"critic": torch.tensor([7.0, 8.0, 9.0])}, {"critic": ~took})
    (first, note), (second, _) = pending.read()
    np.testing.assert_array_equal(first["critic"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(first["actor"], [4.0, 5.0, 6.0])
    np.testing.assert_array_equal(second["critic"], [7.0, 8.0, 9.0])
    assert note["critic"] is took


def test_a_loss_is_copied_when_kept_so_that_nothing_of_the_update_stays_allocated():
    pending = PendingLosses()
    loss = torch.tensor([1.0, 2.0])
    pending.add({"critic": loss})
    loss.fill_(0.0)  # the update's own tensor, freed or reused once the update is over
    np.testing.assert_array_equal(pending.read()[0][0]["critic"], [1.0, 2.0])


def test_the_buffer_is_used_again_after_a_read_back():
    pending = PendingLosses()
    for u in range(3):
        pending.add({"critic": torch.tensor(float(u))})
    pending.read()
    pending.add({"critic": torch.tensor(9.0)})
    assert [losses["critic"] for losses, _ in pending.read()] == [9.0]
