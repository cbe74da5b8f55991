"""Shared builders: small recipes over real environments."""

from __future__ import annotations

import os
from typing import Any

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")
torch.set_num_threads(1)

from layered import Recipe, load_recipe  # noqa: E402


def stack_recipe(periods: list[int], kinds: list[str] | str = "residual-clip", env: str = "Pendulum-v1",
                 **extra: Any) -> Recipe:
    """A recipe whose layers l0 (slowest) .. lN-1 have `periods`; each sees obs and every slower layer."""
    kinds = [kinds] * len(periods) if isinstance(kinds, str) else kinds
    layers = [
        {"name": f"l{k}", "period": p, "sees": ["obs", *[f"l{j}" for j in range(k)]],
         **({"combine": kinds[k]} if k < len(periods) - 1 else {})}
        for k, p in enumerate(periods)
    ]
    return load_recipe({"env": {"id": env}, "layers": layers, **extra})


@pytest.fixture
def tiny() -> list[str]:
    """Overrides that make training a few hundred steps cheap."""
    return ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
            "eval.every=100", "eval.episodes=1"]
