"""A group's replay buffers checkpointed as segments: each checkpoint writes only the rows stored since the
last, a buffer refilled from its segments holds what the original held, and segments nothing names any
more are removed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from layered.checkpoint import CheckpointError, load_checkpoint
from layered.learners.stacked import StackedReplay
from layered.replay_journal import SEGMENT, ReplayJournal, check_segments


def add(replay: StackedReplay, t: int, rows: list[bool] | None = None) -> None:
    """Store row (10 t + k, t) in seed k, for the seeds of `rows` (all by default)."""
    replay.add(np.array([[10 * t + k, t] for k in range(replay.k)], np.float32),
               None if rows is None else np.array(rows))


def assert_same_replay(a: StackedReplay, b: StackedReplay) -> None:
    assert a.stored.tolist() == b.stored.tolist()
    assert torch.equal(a.sizes, b.sizes) and torch.equal(a._next, b._next)
    for k in range(a.k):
        n = int(a.sizes[k])
        assert torch.equal(a._rows[k, :n], b._rows[k, :n]), f"seed {k}"


def test_rows_since_hands_out_each_seeds_new_rows_in_the_order_stored():
    replay = StackedReplay(3, 4, (1, 1), torch.device("cpu"))
    for t, rows in enumerate([None, [True, False, True], [False, False, True], None]):
        add(replay, t, rows)
    # stored: seed 0 at t = 0, 1, 3; seed 1 at 0, 3; seed 2 at 0, 1, 2, 3
    rows, first = replay.rows_since(np.array([1, 0, 2]))
    assert first.tolist() == [1, 0, 2]
    assert rows[:, 0].tolist() == [10, 30, 1, 31, 22, 32]  # seed 0's 2nd and 3rd, seed 1's both, seed 2's last two


def test_rows_since_skips_rows_the_ring_has_overwritten():
    replay = StackedReplay(1, 3, (1, 1), torch.device("cpu"))
    for t in range(5):
        add(replay, t)
    rows, first = replay.rows_since(np.array([0]))
    assert first.tolist() == [2] and rows[:, 0].tolist() == [20, 30, 40]  # rows 0 and 1 were overwritten


@pytest.mark.parametrize("capacity", [3, 100])  # the rings wrap (several times) / never
def test_a_replay_refilled_from_its_segments_holds_what_it_held(tmp_path, capacity):
    original = StackedReplay(3, capacity, (1, 1), torch.device("cpu"))
    journal = ReplayJournal(tmp_path)
    rng = np.random.default_rng(0)
    manifests = {}
    for t in range(20):
        add(original, t, rng.random(3) < 0.6)
        if t % 4 == 3:
            manifests = journal.record({"layer.td3": original})
            journal.prune()
    restored = StackedReplay(3, capacity, (1, 1), torch.device("cpu"))
    ReplayJournal(tmp_path).restore(manifests, {"layer.td3": restored})
    assert_same_replay(original, restored)
    batch = [replay.sample(8, torch.Generator().manual_seed(1)) for replay in (original, restored)]
    assert all(torch.equal(a, b) for a, b in zip(*batch, strict=True))


def test_each_segment_holds_only_the_rows_stored_since_the_last_record(tmp_path):
    replay, journal = StackedReplay(2, 100, (1, 1), torch.device("cpu")), ReplayJournal(tmp_path)
    for t in range(5):
        add(replay, t)
    journal.record({"a.td3": replay})
    add(replay, 5, [True, False])
    manifest = journal.record({"a.td3": replay})["a.td3"]
    assert [s["counts"] for s in manifest["segments"]] == [[5, 5], [1, 0]]
    assert manifest["stored"] == [6, 5] and manifest["written"] == 2
    newest = load_checkpoint(tmp_path / manifest["segments"][-1]["file"], SEGMENT)
    assert newest["rows"].tolist() == [[50.0, 5.0]] and newest["first"] == [5, 5]
    assert journal.record({"a.td3": replay})["a.td3"]["written"] == 2, "nothing new: no segment"


def test_segments_the_ring_overwrote_leave_the_manifest_and_files_unnamed_twice_are_removed(tmp_path):
    replay, journal = StackedReplay(1, 2, (1, 1), torch.device("cpu")), ReplayJournal(tmp_path)
    files = []
    for t in range(4):
        add(replay, t)
        files.append({s["file"] for s in journal.record({"a.td3": replay})["a.td3"]["segments"]})
        journal.prune()
    assert files == [{"a.td3.000000.pt"}, {"a.td3.000000.pt", "a.td3.000001.pt"},
                     {"a.td3.000001.pt", "a.td3.000002.pt"}, {"a.td3.000002.pt", "a.td3.000003.pt"}]
    # the previous checkpoint (files[2]) stays readable: a damaged newest one falls back to it
    assert {p.name for p in tmp_path.iterdir()} == files[2] | files[3]
    (tmp_path / ".a.td3.000009.pt.x").write_bytes(b"left by a crash")
    add(replay, 4)
    journal.record({"a.td3": replay})
    journal.prune()
    assert {p.name for p in tmp_path.iterdir()} == {"a.td3.000002.pt", "a.td3.000003.pt", "a.td3.000004.pt"}


def test_a_checkpoint_whose_segment_is_missing_damaged_or_rewritten_is_refused(tmp_path):
    replay, journal = StackedReplay(1, 10, (1, 1), torch.device("cpu")), ReplayJournal(tmp_path)
    add(replay, 0)
    manifests = journal.record({"a.td3": replay})
    check_segments(tmp_path, manifests)
    path = tmp_path / "a.td3.000000.pt"
    good = path.read_bytes()
    path.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(CheckpointError, match="damaged"):
        check_segments(tmp_path, manifests)
    add(replay, 1)
    ReplayJournal(tmp_path).record({"a.td3": replay})  # another segment written under the same name
    with pytest.raises(CheckpointError, match="not the replay segment the checkpoint was taken with"):
        check_segments(tmp_path, manifests)
    path.unlink()
    with pytest.raises(CheckpointError, match="cannot be read"):
        check_segments(tmp_path, manifests)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_replay_on_the_gpu_refilled_from_its_segments_holds_what_it_held(tmp_path):
    original, journal = StackedReplay(2, 3, (1, 1), torch.device("cuda")), ReplayJournal(tmp_path)
    for t in range(7):
        add(original, t, [True, t % 2 == 0])
        if t % 3 == 2:
            manifests = journal.record({"a.td3": original})
    manifests = journal.record({"a.td3": original})
    restored = StackedReplay(2, 3, (1, 1), torch.device("cuda"))
    ReplayJournal(tmp_path).restore(manifests, {"a.td3": restored})
    assert_same_replay(original, restored)
