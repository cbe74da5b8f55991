"""The cores a process may use: those it may run on, or its share of them where it is one of several
processes a sweep runs side by side on one machine (so that settings sized to the machine, such as
`env.workers = "auto"`, are sized to the share)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

_SHARE: int | None = None
"""The cores this process is given of those it may run on (`share_cores`), None for all of them."""


def share_cores(cores: int) -> None:
    """Tell this process it is one of several sharing the machine and has `cores` of it (a sweep's worker
    does), so that `auto` starts workers for those cores, not for the whole machine."""
    global _SHARE
    _SHARE = max(1, cores)


def usable_cores() -> int:
    """The cores this process may run on, or the share of them it was given (`share_cores`)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return cores if _SHARE is None else min(cores, _SHARE)


@contextmanager
def cores_given(cores: int | None) -> Iterator[None]:
    """Within it, this process has `cores` of the machine (as `share_cores` says; None: as before), and as before
    after it: a command's `--threads` in a process that runs several (a test's)."""
    global _SHARE
    before = _SHARE
    if cores is not None:
        share_cores(cores)
    try:
        yield
    finally:
        _SHARE = before


def trained_threads(threads: int | None) -> int | None:
    """The torch threads to compute with to repeat a run that trained with `threads`: as many, at most this process's
    cores (None where the run did not record them)."""
    return None if not threads else min(threads, usable_cores())


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Within it torch computes with `threads` (None: as before), and as before after it: the products of an
    evaluation sum in an order that depends on the thread count, and so do the last digits of its numbers."""
    import torch

    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
