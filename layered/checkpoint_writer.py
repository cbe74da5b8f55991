"""A checkpoint written beside training: the state is copied where it stands (`host_copy`), and serialising,
checksumming and writing the copy, then removing the files it replaces, go on in a thread while training
continues. One write at a time, in the order asked: the next checkpoint waits for the one before, so the
files on disk are always a whole checkpoint and what it names, as with a checkpoint written in place; a
process killed mid-write leaves the checkpoint before it, which resumes. An error of a write is raised
where the next one is asked for, or where the writer closes.

That pays where training leaves a core free for the write (`writes_beside`); where every core computes
updates, the write took as much from them as it saved, so there it is written in place."""

from __future__ import annotations

import sys
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType
from typing import Any

import numpy as np
import torch

from layered.cores import usable_cores


def host_copy(tree: Any, tensors: bool = True) -> Any:
    """A copy of `tree` that its owner may go on changing: its tensors copied to the host, its numpy arrays as
    tensors (which a checkpoint loaded weights-only can hold); dicts, lists and tuples copied, the rest kept
    (numbers and strings, which do not change). With `tensors` False the tensors themselves are kept, for a
    state written before its owner goes on."""
    if isinstance(tree, torch.Tensor):
        return tree.detach().to("cpu", copy=True) if tensors else tree
    if isinstance(tree, np.ndarray):
        return torch.from_numpy(np.array(tree, order="C", copy=True))
    if isinstance(tree, dict):
        return {key: host_copy(value, tensors) for key, value in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(host_copy(value, tensors) for value in tree)
    return tree


def as_arrays(tree: Any) -> Any:
    """`tree` with its tensors as numpy arrays again: what `host_copy` was given, once its copy is read back."""
    if isinstance(tree, torch.Tensor):
        return tree.numpy()
    if isinstance(tree, dict):
        return {key: as_arrays(value) for key, value in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(as_arrays(value) for value in tree)
    return tree


def writes_beside(device: torch.device) -> bool:
    """Whether checkpoints are written beside training: where it leaves a core free for them, its updates on a GPU
    or on fewer torch threads than the process has cores. (A 32-seed Hopper group on a 2-core CPU spent 6.7 s of
    its 47 in checkpoints written in place and 4.8 s written beside its one torch thread, but with two torch
    threads the writes slowed the updates by more than they saved: docs/performance.md.)"""
    return device.type == "cuda" or torch.get_num_threads() < usable_cores()


class CheckpointWriter:
    """Writes one checkpoint at a time, in a thread of its own where `beside` (else in place, when asked); a
    context manager that waits for the last."""

    def __init__(self, beside: bool = True) -> None:
        self.beside = beside
        self._pool = ThreadPoolExecutor(1, "layered-checkpoint") if beside else None
        self._writing: Future[None] | None = None

    def start(self, write: Callable[[], None]) -> None:
        """Once the write under way is done, start `write` (which writes a copy where `beside`: see `host_copy`)."""
        self.wait()
        if self._pool is None:
            write()
        else:
            self._writing = self._pool.submit(write)

    def wait(self) -> None:
        """Wait for the write under way; its error, if it failed."""
        writing, self._writing = self._writing, None
        if writing is not None:
            writing.result()

    def __enter__(self) -> CheckpointWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        """Wait for the last write; where something else already went wrong, its failure is a warning."""
        try:
            self.wait()
        except Exception as failure:
            if error is None:
                raise
            print(f"layered: warning: the last checkpoint was not written ({failure})", file=sys.stderr)
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
