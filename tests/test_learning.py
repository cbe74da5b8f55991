"""Long learning checks on the paper's Pendulum budgets; run on request with `pytest -m slow`."""

import json
from pathlib import Path

import pytest

from layered import load_recipe, train

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"


def final(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())["phases"][-1]


@pytest.mark.slow
def test_pendulum_tla_c_learns_and_repeats_far_more_than_td3(tmp_path):
    train(load_recipe(PENDULUM / "td3.toml"), tmp_path / "td3", progress=False)
    train(load_recipe(PENDULUM / "tla-c.toml"), tmp_path / "tla-c", progress=False)
    td3, final_run = final(tmp_path / "td3"), final(tmp_path / "tla-c")
    assert final_run["return_mean"] > -300  # paper: -152.6 +- 28.2 over seeds
    assert final_run["repetition"] > 0.4 and td3["repetition"] < 0.2  # paper: 71% vs 6%


@pytest.mark.slow
def test_pendulum_tla_o_makes_fewer_decisions_than_td3(tmp_path):
    train(load_recipe(PENDULUM / "tla-o.toml"), tmp_path / "tla-o", progress=False)
    result = final(tmp_path / "tla-o")
    assert result["return_mean"] > -400
    assert result["decisions"] < result["episode_steps"]  # TD3 decides at every step
