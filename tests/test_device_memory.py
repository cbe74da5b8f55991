"""The GPU benchmark's memory figures (benchmarks/device_memory.py), with `nvidia-smi` stood in for by a script
that reports the processes of a file the test writes."""

import os
import stat
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from device_memory import DeviceMemory, mib, parse


def fake_nvidia_smi(folder: Path, report: Path) -> None:
    """An `nvidia-smi` in `folder` that prints `report`'s lines, as `--query-compute-apps` prints them."""
    script = folder / "nvidia-smi"
    script.write_text(f"#!/bin/sh\ncat {report}\n")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)


def test_lines_are_read_as_pids_and_mib_and_unknown_values_left_out():
    assert parse("11, 512\n12, [N/A]\n13, 1024.5\n\n") == {11: 512.0, 13: 1024.5}


def test_each_new_process_keeps_its_peak_and_those_there_before_are_left_out(tmp_path, monkeypatch):
    report = tmp_path / "report"
    report.write_text("7, 900\n")  # a process there before the block
    fake_nvidia_smi(tmp_path, report)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ['PATH']}")
    with DeviceMemory(every=0.01) as memory:
        for lines in ("7, 900\n21, 300\n", "7, 900\n21, 700\n22, 500\n", "7, 900\n21, 400\n"):
            (tmp_path / "next").write_text(lines)
            os.replace(tmp_path / "next", report)  # (whole, never read half written)
            time.sleep(0.2)
    assert memory.peaks == {21: 700.0, 22: 500.0}
    assert memory.largest() == 700.0 and memory.total() == 1200.0
    assert mib(memory.total(), 4) == "300"


def test_without_nvidia_smi_nothing_is_measured(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with DeviceMemory(every=0.01) as memory:
        time.sleep(0.05)
    assert not memory.available and memory.largest() is None and mib(memory.total()) == "n/a"
