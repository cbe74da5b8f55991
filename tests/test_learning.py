"""Learning checks on the authors' Pendulum budgets: `pytest -m learning` (CI's learning step, TLA-C: 13 minutes
on 2 cores where the CPU trains in float32), and longer ones on request with
`pytest -m slow` (TD3 at its budget beside it, TLA-O)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from layered import load_recipe, train

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"


def final(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())["phases"][-1]


# The paper's Pendulum-v1 results (Tables 1 and 2): mean and std of the return over seeds, action repetition.
PAPER = {"td3": (-150.93, 27.28, 0.0604), "tla-c": (-152.58, 28.22, 0.7096)}


def mean_repetition_of_two_seeds(method: str, out: Path) -> float:
    """Seeds 0 and 1 of `method` at its recipe's budget (one sweep, two processes), each seed's final return
    asserted within three of the paper's standard deviations of its mean; their action repetition on average,
    as the paper's table reports it (one seed alone spreads widely: from 48% to 73% over eight TLA-C seeds,
    docs/experiments.md)."""
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "sweep", str(PENDULUM / f"{method}.toml"),
                           "--seeds", "2", "--jobs", "2", "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    mean, std, _ = PAPER[method]
    results = [final(out / "pendulum" / method / f"seed{seed}") for seed in (0, 1)]
    for seed, result in enumerate(results):
        assert result["return_mean"] > mean - 3 * std, (method, seed, result["return_mean"])
    return sum(result["repetition"] for result in results) / len(results)


@pytest.mark.learning
@pytest.mark.timeout(1800)  # beyond the suite's 600 s per test
def test_pendulum_tla_c_learns_as_the_paper_reports_repeating_most_of_its_actions(tmp_path):
    """At least 51% of its actions repeated: the paper's 71% less 20 points."""
    repetition = mean_repetition_of_two_seeds("tla-c", tmp_path / "sweep")
    assert repetition > PAPER["tla-c"][2] - 0.2, repetition


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_pendulum_td3_learns_as_the_paper_reports_repeating_few_of_its_actions(tmp_path):
    """At most 21% of its actions repeated: the paper's 6% and 15 points."""
    repetition = mean_repetition_of_two_seeds("td3", tmp_path / "sweep")
    assert repetition < PAPER["td3"][2] + 0.15, repetition


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_pendulum_tla_o_makes_fewer_decisions_than_td3(tmp_path):
    train(load_recipe(PENDULUM / "tla-o.toml"), tmp_path / "tla-o", progress=False)
    result = final(tmp_path / "tla-o")
    assert result["return_mean"] > -400
    assert result["decisions"] < result["episode_steps"]  # TD3 decides at every step
