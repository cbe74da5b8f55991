"""A checkpoint written beside training: what is written is the state where it was copied, writes happen
one at a time in the order asked, and a failed write is raised where the next one is asked for or at the end."""

import threading

import numpy as np
import pytest
import torch

from layered import checkpoint_writer
from layered.checkpoint_writer import CheckpointWriter, host_copy, writes_beside


def test_a_host_copy_keeps_the_state_where_it_was_copied():
    weights, counts = torch.arange(6.0).reshape(2, 3), np.array([1, 2, 3])
    state = {"nets": {"actor": weights}, "counts": counts, "moments": [weights * 2, (counts, "adam")], "step": 7}
    copy = host_copy(state)
    weights += 100  # the owner goes on training
    counts[:] = 0
    state["nets"]["critic"] = weights
    state["moments"].append(1)
    assert torch.equal(copy["nets"]["actor"], torch.arange(6.0).reshape(2, 3)) and list(copy["nets"]) == ["actor"]
    assert isinstance(copy["counts"], torch.Tensor) and copy["counts"].tolist() == [1, 2, 3]  # arrays as tensors
    assert len(copy["moments"]) == 2 and isinstance(copy["moments"][1], tuple)
    assert copy["moments"][1][0].tolist() == [1, 2, 3] and copy["moments"][1][1] == "adam" and copy["step"] == 7


def test_a_host_copy_of_a_strided_array_is_contiguous():
    copy = host_copy(np.arange(12.0).reshape(3, 4)[:, ::2])
    assert copy.is_contiguous() and copy.tolist() == [[0.0, 2.0], [4.0, 6.0], [8.0, 10.0]]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_a_host_copy_of_a_gpu_tensor_is_on_the_host():
    weights = torch.ones(3, device="cuda")
    copy = host_copy({"w": weights})
    weights += 1
    assert copy["w"].device.type == "cpu" and copy["w"].tolist() == [1.0, 1.0, 1.0]


def test_writes_run_beside_the_caller_one_at_a_time_in_the_order_asked():
    order, first_may_end = [], threading.Event()

    def write(name: str, wait: threading.Event | None = None):
        def run():
            if wait is not None:
                assert wait.wait(5)
            order.append(name)
        return run

    with CheckpointWriter() as writer:
        writer.start(write("first", first_may_end))
        order.append("the caller goes on")  # while the first write waits
        first_may_end.set()
        writer.start(write("second"))  # waits for the first
        assert order[:2] == ["the caller goes on", "first"]
    assert order == ["the caller goes on", "first", "second"]  # the last waited for at the end


def test_a_failed_write_is_raised_where_the_next_is_asked_for():
    def fail():
        raise OSError("No space left on device")

    with CheckpointWriter() as writer:
        writer.start(fail)
        with pytest.raises(OSError, match="No space left"):
            writer.start(lambda: None)


def test_a_failed_last_write_is_raised_at_the_end_or_warned_of_beside_another_error(capsys):
    def fail():
        raise OSError("No space left on device")

    with pytest.raises(OSError, match="No space left"), CheckpointWriter() as writer:
        writer.start(fail)
    with pytest.raises(KeyboardInterrupt), CheckpointWriter() as writer:
        writer.start(fail)
        raise KeyboardInterrupt
    assert "the last checkpoint was not written (No space left on device)" in capsys.readouterr().err


def test_a_writer_that_writes_in_place_is_done_when_start_returns():
    order = []
    with CheckpointWriter(beside=False) as writer:
        writer.start(lambda: order.append("written"))
        order.append("the caller goes on")
    assert order == ["written", "the caller goes on"]


@pytest.mark.parametrize("device, threads, cores, beside", [
    ("cpu", 2, 2, False),  # every core computes updates: in place
    ("cpu", 1, 2, True),  # a core left free
    ("cuda", 16, 16, True),  # the updates on the GPU
])
def test_checkpoints_are_written_beside_training_where_it_leaves_a_core_free(device, threads, cores, beside,
                                                                            monkeypatch):
    monkeypatch.setattr(checkpoint_writer.torch, "get_num_threads", lambda: threads)
    monkeypatch.setattr(checkpoint_writer, "usable_cores", lambda: cores)
    assert writes_beside(torch.device(device)) is beside


def test_a_copy_for_a_write_in_place_keeps_the_tensors_and_copies_the_rest():
    weights, counts = torch.ones(2), np.array([1, 2])
    copy = host_copy({"w": weights, "n": counts}, tensors=False)
    counts[:] = 0
    assert copy["w"] is weights and copy["n"].tolist() == [1, 2]
