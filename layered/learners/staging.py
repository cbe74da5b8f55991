"""Host arrays handed to a GPU without stalling the host. A copy from ordinary (pageable) host memory waits
for every kernel queued before it, so each observation, transition and mask a group sent that way made the
host wait for the update in flight; a copy from page-locked memory is queued like a kernel instead."""

from __future__ import annotations

import numpy as np
import torch


class Staging:
    """Float32 arrays' way to one device: on a GPU, through a page-locked buffer per shape, copied in stream
    order into a device tensor of that shape that stays where it is; on a CPU, the array itself as a tensor."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self._buffers: dict[tuple[int, ...], tuple[torch.Tensor, torch.Tensor, torch.cuda.Event]] = {}

    def put(self, array: np.ndarray) -> torch.Tensor:
        """`array` as a float32 tensor on the device. On a GPU the tensor is the same one at every call of a
        shape (valid until the next such call), and the host returns before the copy has run."""
        array = np.ascontiguousarray(array, np.float32)
        if self.device.type != "cuda":
            return torch.from_numpy(array)
        if array.shape not in self._buffers:
            with torch.inference_mode(False):  # ordinary tensors, written in and out of inference mode alike
                self._buffers[array.shape] = (torch.empty(array.shape, pin_memory=True),
                                              torch.empty(array.shape, device=self.device), torch.cuda.Event())
        host, tensor, copied = self._buffers[array.shape]
        copied.synchronize()  # the last copy out of the page-locked buffer has run: it may be written again
        host.numpy()[...] = array
        tensor.copy_(host, non_blocking=True)
        copied.record()
        return tensor
