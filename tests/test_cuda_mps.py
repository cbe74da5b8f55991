"""CUDA MPS around a sweep's workers on one GPU: started where its control program is installed and it is
not running, quit at the end; otherwise one line on how. A stand-in control program records its calls."""

import stat
from pathlib import Path

import pytest

from layered.cuda_mps import CONTROL, shared_gpu
from layered.recipe import load_recipe, resolved
from layered.sweep import Job, on_gpu

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def control(tmp_path, monkeypatch):
    """A stand-in `nvidia-cuda-mps-control` on PATH that logs each call (arguments, then stdin) and exits with
    the code in `exit-code`; MPS's pipe directory in tmp_path."""
    bin_dir, log = tmp_path / "bin", tmp_path / "calls.log"
    bin_dir.mkdir()
    program = bin_dir / CONTROL
    program.write_text(f'#!/bin/sh\necho "args: $*" >> {log}\nif [ "$1" != "-d" ]; then cat >> {log}; fi\n'
                       f'echo "no GPU" >&2\nexit $(cat {tmp_path / "exit-code"})\n')
    program.chmod(program.stat().st_mode | stat.S_IEXEC)
    (tmp_path / "exit-code").write_text("0")
    monkeypatch.setenv("PATH", f"{bin_dir}:/usr/bin:/bin")
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(tmp_path / "pipe"))
    return log


def test_mps_is_started_for_the_workers_and_quit_at_the_end(control):
    with shared_gpu(4) as line:
        assert line == "started CUDA MPS for the 4 workers (quit again when the sweep ends)"
        assert control.read_text() == "args: -d\n"
    assert control.read_text() == "args: -d\nargs: \nquit\n"


def test_a_running_mps_is_used_and_left_running(control, tmp_path):
    (tmp_path / "pipe").mkdir()
    (tmp_path / "pipe" / "control").touch()
    with shared_gpu(2) as line:
        assert line == "CUDA MPS is running: the 2 workers share the GPU at once"
    assert not control.exists()


def test_mps_that_does_not_start_or_is_not_installed_is_one_line_and_the_sweep_goes_on(control, tmp_path,
                                                                                        monkeypatch):
    (tmp_path / "exit-code").write_text("1")
    with shared_gpu(3) as line:
        assert line == f"CUDA MPS did not start (`{CONTROL} -d`: no GPU); the 3 workers take turns on the GPU"
    assert control.read_text() == "args: -d\n"  # nothing to quit
    (tmp_path / "empty").mkdir()  # a PATH with no control program (a GPU machine may have one in /usr/bin)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    with shared_gpu(3) as line:
        assert "take turns on the GPU" in line and f"`{CONTROL} -d`" in line
    with shared_gpu(1) as line:  # one worker has the GPU to itself
        assert line is None


def test_only_a_sweep_whose_learners_run_on_a_gpu_of_this_machine_shares_one(monkeypatch):
    def job(device):
        recipe = load_recipe(ROOT / "recipes/pendulum/tla-c.toml", [f"layers.fast.learner.device={device}"])
        return Job(resolved(recipe), Path("out"), f"tla-c-{device}", None)

    monkeypatch.setattr("torch.cuda.is_available", lambda: True)
    assert on_gpu([job("cpu"), job("auto")]) and not on_gpu([job("cpu")])
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    assert not on_gpu([job("auto")])
