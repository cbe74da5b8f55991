"""A group's replay buffers: rows stored per seed under a mask, counted and wrapped per seed, on the CPU and
(where there is one) through page-locked staging on a GPU, with the same contents."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from layered.learners.stacked import StackedReplay
from layered.learners.staging import Staging

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def filled(device: str) -> StackedReplay:
    """Three seeds, two slots each, rows of widths (1, 2); five adds, traced by hand below."""
    replay = StackedReplay(3, 2, (1, 2), torch.device(device))
    for t, rows in enumerate([None, np.array([True, False, True]), np.array([False, False, False]),
                              np.array([True, False, False]), np.ones(3, bool)]):
        replay.add(np.array([[10 * t + k, t, -k] for k in range(3)], np.float32), rows)
    return replay


def test_a_masked_add_stores_and_counts_only_the_seeds_it_names():
    replay = filled("cpu")
    # seed 0 stored at t = 0, 1, 3, 4: slots 0 1 0 1 -> [30, 40]; seed 1 at t = 0, 4 -> [1, 41];
    # seed 2 at t = 0, 1, 4: slots 0 1 0 -> [42, 12]
    assert replay.stored.tolist() == [4, 2, 3]
    assert replay.sizes.tolist() == [2, 2, 2]
    assert replay._next.tolist() == [0, 0, 1]
    assert replay._rows[:, :, 0].tolist() == [[30, 40], [1, 41], [42, 12]]
    obs, rest = replay.seed_rows(2)
    assert obs[:, 0].tolist() == [42, 12] and rest.tolist() == [[4, -2], [1, -2]]


def test_a_seed_that_stored_nothing_has_nothing_to_sample():
    replay = StackedReplay(2, 4, (1,), torch.device("cpu"))
    replay.add(np.array([[5.0], [6.0]], np.float32), np.array([False, True]))
    assert replay.sizes.tolist() == [0, 1] and replay.stored.tolist() == [0, 1]
    (rows,) = replay.sample(8, torch.Generator().manual_seed(0))
    assert rows[1].flatten().tolist() == [6.0] * 8


def test_each_seed_samples_whole_rows_of_its_own():
    replay = filled("cpu")  # seed 0 holds rows (30 | 3, 0) and (40 | 4, 0); seed 1 (1 | 0, -1), (41 | 4, -1) ...
    first, rest = replay.sample(64, torch.Generator().manual_seed(0))
    assert first.shape == (3, 64, 1) and rest.shape == (3, 64, 2)
    held = [{(30, 3, 0), (40, 4, 0)}, {(1, 0, -1), (41, 4, -1)}, {(42, 4, -2), (12, 1, -2)}]
    for k in range(3):
        drawn = {tuple(int(x) for x in row) for row in torch.cat([first[k], rest[k]], dim=1).tolist()}
        assert drawn == held[k]  # (64 draws from two rows: both drawn, and nothing else)


def test_staging_on_a_cpu_hands_over_the_array_as_float32():
    staged = Staging(torch.device("cpu")).put(np.array([[1, 2]], np.float64))
    assert staged.dtype == torch.float32 and staged.tolist() == [[1.0, 2.0]]


def test_staging_into_a_tensor_of_the_callers_fills_and_returns_it():
    out = torch.zeros(2, 2)
    assert Staging(torch.device("cpu")).put(np.array([[1, 2], [3, 4]], bool), out=out) is out
    assert out.tolist() == [[1.0, 1.0], [1.0, 1.0]]


class FakeEvent:
    """Stands for a CUDA event on a CPU: what was asked of it, in order."""

    def __init__(self, log):
        self.log = log

    def synchronize(self):
        self.log.append("synchronize")

    def record(self, stream=None):
        self.log.append(("record", stream))


def test_staging_to_a_gpu_waits_for_a_buffers_last_copy_and_finds_the_stream_by_the_devices_index(monkeypatch):
    """The bookkeeping of the GPU path, with torch.cuda's events and streams and page-locked memory stood in for:
    each copy's event recorded on the current stream looked up by index (torch walks to the current device in
    Python when given none), and a buffer written again only once its last copy has run."""
    log, empty = [], torch.empty
    monkeypatch.setattr(torch.cuda, "Event", lambda: FakeEvent(log))
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 2)
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: f"stream of {device}")
    monkeypatch.setattr(torch, "empty", lambda shape, pin_memory=False: empty(shape))
    staging, out = Staging(torch.device("cuda")), torch.zeros(3)
    for t in range(2):
        assert staging.put(np.full(3, t), out=out) is out and out.tolist() == [t] * 3
    assert log == ["synchronize", ("record", "stream of 2")] * 2
    assert Staging(torch.device("cuda:1")).put(np.zeros(1), out=torch.zeros(1)) is not None
    assert log[-1] == ("record", "stream of 1")


@cuda
def test_a_replay_on_the_gpu_holds_what_one_on_the_cpu_holds():
    on_gpu, on_cpu = filled("cuda"), filled("cpu")
    for name in ("_rows", "sizes", "_next"):
        assert torch.equal(getattr(on_gpu, name).cpu(), getattr(on_cpu, name))


@cuda
def test_staged_arrays_reach_the_gpu_in_order_though_they_share_one_buffer():
    staging, device = Staging(torch.device("cuda")), torch.device("cuda")
    total = torch.zeros(4, device=device)
    for t in range(50):
        total += staging.put(np.full(4, t, np.float32))  # queued behind the copy, before the next one
    assert total.tolist() == [sum(range(50))] * 4


@cuda
def test_staged_arrays_reach_a_tensor_of_the_callers_in_order():
    staging, into = Staging(torch.device("cuda")), torch.zeros(4, device="cuda")
    total = torch.zeros(4, device="cuda")
    for t in range(50):
        total += staging.put(np.full(4, t, np.float32), out=into)
    assert total.tolist() == [sum(range(50))] * 4


@cuda
def test_staging_on_a_side_stream_reuses_its_buffer_only_once_that_streams_copy_has_run():
    """The copies queue behind a long kernel on the side stream: a buffer freed by an event of another stream
    (the default one, idle) would be written again before they ran, and they would all read the last array."""
    staging, side = Staging(torch.device("cuda")), torch.cuda.Stream()
    with torch.cuda.stream(side):
        total = torch.zeros(4, device="cuda")
        torch.cuda._sleep(10**8)
        for t in range(20):
            total += staging.put(np.full(4, t, np.float32))
    side.synchronize()
    assert total.tolist() == [sum(range(20))] * 4


def replayed(device: str, captured: bool) -> StackedReplay:
    """Four seeds, three slots each: 24 adds of every seed's rows and of masks (all, none, some) drawn at random,
    so that each kind of store is captured (after its first eager calls) and replayed, and the buffers wrap."""
    replay = StackedReplay(4, 3, (2, 1), torch.device(device), captured=captured)
    rng = np.random.default_rng(0)
    for t in range(24):
        rows = None if t % 3 == 0 else rng.random(4) < 0.6 if t % 3 == 1 else np.ones(4, bool) if t % 6 == 2 else None
        replay.add(rng.normal(size=(4, 3)).astype(np.float32), rows)
    return replay


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=cuda)])
def test_a_captured_store_holds_what_an_eager_one_holds(device):
    captured, eager = replayed(device, True), replayed("cpu", False)
    assert captured.stored.tolist() == eager.stored.tolist()
    for name in ("_rows", "sizes", "_next"):
        assert torch.equal(getattr(captured, name).cpu(), getattr(eager, name))
    if device == "cuda":
        assert all(step.captured for step in captured._stores.values()) and len(captured._stores) == 2
