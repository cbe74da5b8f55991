"""The precision of a learner's updates: what `precision = "auto"` means on a device, and the regions that
compute the updates' products in it (bfloat16 under autocast; float32 products in TF32 on a GPU)."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import torch

# Linux's names (in /proc/cpuinfo) for CPUs that multiply bfloat16 in hardware: x86's AVX-512 BF16 and AMX, Arm's BF16
CPU_BFLOAT16_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


@functools.cache  # read once per process, not once per learner (a group of K seeds builds K of each layer's)
def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (x86 `flags`, Arm `Features`); none where it does not."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return frozenset()
    return frozenset(flag for line in lines if line.startswith(("flags", "Features"))
                     for flag in line.partition(":")[2].split())


def native_bfloat16(device: torch.device) -> bool:
    """Whether `device` multiplies bfloat16 in hardware (emulated bfloat16 is slower than float32)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    return device.type == "cpu" and not CPU_BFLOAT16_FLAGS.isdisjoint(cpu_flags())


def resolve_precision(name: str, device: torch.device) -> str:
    """The precision a `precision` setting computes in on `device`: `auto` is bfloat16 where the device
    multiplies it natively, float32 elsewhere; `tf32` is refused off a GPU."""
    if name == "tf32" and device.type != "cuda":
        raise ValueError(f"precision 'tf32' needs the learner on a GPU (its device is {device.type!r})")
    if name != "auto":
        return name
    return "bfloat16" if native_bfloat16(device) else "float32"


def loaded_precision(setting: str, current: str, state: dict[str, Any]) -> str:
    """The precision to go on in after loading a checkpoint's `state`: with `auto`, the one it was trained in
    (so that a run resumes exactly wherever it resumes; older checkpoints lack it), else the one named."""
    return state.get("precision", current) if setting == "auto" else current


def autocast(precision: str, device: torch.device, cache: bool = True) -> torch.autocast:
    """The region computing the updates' products in bfloat16 where `precision` (a resolved one) is bfloat16;
    weights, optimiser moments and acting stay float32. `cache=False` for a step captured as a CUDA graph,
    which forbids autocast's cache of casts."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16", cache_enabled=cache)


def update_region(precision: str) -> AbstractContextManager[Any]:
    """The region around a whole update (its compiled or captured steps included, which cannot change torch's
    global settings themselves): with `tf32`, float32 products in TensorFloat-32 on the GPU (torch's float32
    matmul precision "high"), and the process's own setting again after it, so that acting stays float32."""
    return tf32_products() if precision == "tf32" else contextlib.nullcontext()


@contextlib.contextmanager
def tf32_products() -> Iterator[None]:
    """torch's float32 matmul precision "high" (TF32 on a GPU) while the region runs, the process's after it."""
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)
