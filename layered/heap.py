"""The C heap of a process that trains a group of seeds: freed memory kept for reuse.

A group's update allocates and frees tensors of a few MB each many times a step (bfloat16 casts of
`[K, in, out]` weights, gradients, activations). glibc's malloc hands blocks that large back to the
system when they are freed (unmapping them, or trimming the heap's top), so the next step's blocks
fault their pages in again: some 300 page faults an update of a 4-seed Pendulum group, 6% of its time
on one core. Keeping blocks below 32 MB on the heap and the heap's freed top up to 1 GB ends that;
the memory a group holds is then its peak, which it reaches every step anyway.
"""

from __future__ import annotations

import ctypes
import sys

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 2**20
"""Blocks this large and larger are mapped on their own and unmapped when freed (glibc's largest setting)."""

TRIM_THRESHOLD = 2**30
"""Free memory at the heap's top beyond this is handed back to the system."""


def keep_freed_memory() -> bool:
    """Have this process's malloc keep freed blocks for reuse (see the module's docstring); False where it
    is not glibc's malloc (macOS, musl), which is then left as it is."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # setting either threshold also stops glibc from moving them with the sizes it sees freed
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
