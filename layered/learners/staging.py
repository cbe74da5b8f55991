"""Host arrays handed to a GPU without stalling the host. A copy from ordinary (pageable) host memory waits
for every kernel queued before it, so each observation, transition and mask a group sent that way made the
host wait for the update in flight; a copy from page-locked memory is queued like a kernel instead."""

from __future__ import annotations

import numpy as np
import torch


class Staging:
    """Float32 arrays' way to one device: on a GPU, through a page-locked buffer per shape, copied in stream
    order into a device tensor (of that shape, that stays where it is, or the caller's); on a CPU, the array
    itself as a tensor."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        # the device's index, by which each copy's stream is looked up (without one, torch finds the device in Python)
        self._index = (device.index if device.index is not None else torch.cuda.current_device()
                       ) if device.type == "cuda" else None
        self._buffers: dict[tuple[int, ...], tuple[torch.Tensor, torch.cuda.Event]] = {}
        self._tensors: dict[tuple[int, ...], torch.Tensor] = {}

    def put(self, array: np.ndarray, out: torch.Tensor | None = None) -> torch.Tensor:
        """`array` as a float32 tensor on the device: copied into `out` (a float32 tensor of its shape there) if
        given, and returned. On a GPU the tensor is otherwise the same one at every call of a shape (valid until
        the next such call), and the host returns before the copy has run."""
        array = np.ascontiguousarray(array, np.float32)
        if self.device.type != "cuda":
            staged = torch.from_numpy(array)
            return staged if out is None else out.copy_(staged)
        if array.shape not in self._buffers:
            with torch.inference_mode(False):  # ordinary tensors, written in and out of inference mode alike
                self._buffers[array.shape] = (torch.empty(array.shape, pin_memory=True), torch.cuda.Event())
        host, copied = self._buffers[array.shape]
        copied.synchronize()  # the last copy out of the page-locked buffer has run: it may be written again
        host.numpy()[...] = array
        if out is None:
            out = self._tensor(array.shape)
        out.copy_(host, non_blocking=True)
        copied.record(torch.cuda.current_stream(self._index))
        return out

    def _tensor(self, shape: tuple[int, ...]) -> torch.Tensor:
        """The device tensor that arrays of `shape` are copied into when the caller gives none."""
        if shape not in self._tensors:
            with torch.inference_mode(False):
                self._tensors[shape] = torch.empty(shape, device=self.device)
        return self._tensors[shape]
