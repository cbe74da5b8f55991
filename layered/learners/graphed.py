"""A learner's update replayed as one CUDA graph: its kernels launched by a single call instead of one
launch per operation, which is what bounds a small network's update on a GPU.

The step handed to `GraphedStep` takes no arguments: it reads everything from tensors that stay where
they are (networks, moments, replay rows, masks that the caller fills in place before each call) and
returns tensors. It must not read a value back to the host (`.item()`, `bool(t)`, `.cpu()`), draw
from a generator the graph does not know, or make shapes that depend on values; `tests/test_graphed.py`
checks a group's update for all three on any machine. The step's first `eager` calls run as they are,
so that lazily made state (gradients, optimiser moments, library handles) exists before the capture;
the next call captures it, and every call from then on replays it. A replay hands out the graph's own
output tensors, which the next replay overwrites: a caller that keeps them copies them.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Generic, TypeVar

import torch

Out = TypeVar("Out")


class GraphedStep(Generic[Out]):
    """`step` run eagerly `eager` times, then captured as a CUDA graph and replayed; on a CPU, always eager."""

    def __init__(self, step: Callable[[], Out], device: torch.device, generators: Sequence[torch.Generator] = (),
                 eager: int = 3) -> None:
        """`generators`: those `step` draws from, registered with the graph so that each replay advances them."""
        self.step, self.device, self.generators, self.eager = step, device, list(generators), eager
        self.calls = 0
        self.graph: torch.cuda.CUDAGraph | None = None
        self.stream: torch.cuda.Stream | None = None
        self.outputs: Out | None = None

    @property
    def captured(self) -> bool:
        """Whether the step has been captured as a CUDA graph (it replays the graph from then on)."""
        return self.graph is not None

    def __call__(self) -> Out:
        """One step; its outputs (once replayed, the graph's own, until the next replay)."""
        self.calls += 1
        if self.device.type != "cuda":
            return self.step()
        if self.calls <= self.eager:
            return self._on_capture_stream(self.step)
        if self.graph is None:
            self._on_capture_stream(self._capture)
        assert self.graph is not None
        self.graph.replay()
        return self.outputs  # type: ignore[return-value]

    def _on_capture_stream(self, work: Callable[[], Out]) -> Out:
        """`work` on the stream the capture uses (libraries keep handles per stream: the eager calls make
        them there, before the capture), ordered after and before the current stream's work."""
        if self.stream is None:
            self.stream = torch.cuda.Stream(self.device)
        current = torch.cuda.current_stream(self.device)
        self.stream.wait_stream(current)
        with torch.cuda.stream(self.stream):
            out = work()
        current.wait_stream(self.stream)
        return out

    def _capture(self) -> Out:
        """Record the step's kernels (nothing runs while they are recorded: the replay that follows runs them)."""
        graph = torch.cuda.CUDAGraph()
        register_generators(graph, self.generators)
        with torch.cuda.graph(graph, stream=self.stream):
            self.outputs = self.step()
        self.graph = graph
        return self.outputs


def register_generators(graph: torch.cuda.CUDAGraph, generators: Sequence[torch.Generator]) -> None:
    """Register `generators` with `graph`, so that each replay advances them. torch 2.14 registers a generator
    by itself at its first draw in a capture and deprecates doing it by hand (a call that does nothing and
    warns); where the method is gone, nothing is left to do."""
    register = getattr(graph, "register_generator_state", None)
    if register is None:
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        for generator in generators:
            register(generator)
