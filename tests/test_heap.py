"""The heap setting of a group's process: freed blocks of MBs taken back without faulting their pages in again."""

import platform
import resource
import subprocess
import sys

import pytest

# A fresh process frees ten 3 MB blocks a round, as a group's update frees its casts and gradients; glibc's
# malloc hands them back to the system (the heap's free top beyond twice the largest block freed), so that
# every round faults their pages in again. It prints its page faults per round after the first.
ROUNDS = """
import resource, sys
from layered.heap import keep_freed_memory
if sys.argv[1] == "kept":
    assert keep_freed_memory()
blocks = [bytearray(3_000_000) for _ in range(10)]
del blocks
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    blocks = [bytearray(3_000_000) for _ in range(10)]
    del blocks
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / 10)
"""


def faults_per_round(setting: str) -> float:
    out = subprocess.run([sys.executable, "-c", ROUNDS, setting], capture_output=True, text=True, check=True)
    return float(out.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the setting is glibc malloc's")
def test_freed_blocks_are_taken_back_without_page_faults() -> None:
    pages = 10 * 3_000_000 // resource.getpagesize()
    assert faults_per_round("default") > pages / 2  # (what the setting is for: glibc as it comes)
    assert faults_per_round("kept") < 10


def test_the_heap_is_left_alone_where_it_is_not_glibcs(monkeypatch: pytest.MonkeyPatch) -> None:
    from layered import heap

    monkeypatch.setattr(heap.sys, "platform", "darwin")
    assert heap.keep_freed_memory() is False
