"""What one step of the stack's rules costs for K stacks at once: the per-step bookkeeping of every
decision, the walk through the combiners and each layer's shaped reward, with made-up outputs in
place of policies (the networks are not timed).

    python benchmarks/rules_batch.py                                # the 2-layer Pendulum TLA-C stack
    python benchmarks/rules_batch.py hopper/tla-realtime.toml       # the real-time Hopper stack (delays)

Per K: the best of 5 timings of 500 steps, and the same per stack.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import layered
from layered.envs import make_env
from layered.rules import Rules
from layered.stack import Stack

RECIPES = Path(__file__).resolve().parent.parent / "recipes"


def main() -> None:
    name = sys.argv[1] if len(sys.argv) > 1 else "pendulum/tla-c.toml"
    recipe = layered.load_recipe(RECIPES / name)
    env = make_env(recipe.env.id)
    stack = Stack(recipe, env.observation_space, env.action_space, evaluation=True)
    low, high, dim = env.action_space.low, env.action_space.high, env.observation_space.shape[0]
    env.close()
    print(f"{name}: one step of the rules\n| K | µs per step, all K stacks | µs per stack |\n|---|---|---|")
    for k in (1, 4, 16, 64, 256):
        rules = Rules(stack.rules.layers, stack.rules.active, low, high, k)
        rng = np.random.default_rng(0)
        obs = rng.normal(size=(k, dim)).astype(np.float32)
        outputs = {i: rng.uniform(layer.low, layer.high, (k, layer.size)).astype(np.float32)
                   for i, layer in enumerate(rules.layers)}

        def act(i: int, seen: np.ndarray, rows: np.ndarray, outputs: dict = outputs) -> np.ndarray:
            return outputs[i][rows]

        best = float("inf")
        for attempt in range(6):  # the first warms up
            start = time.perf_counter()
            for _ in range(500):
                rules.decide_all(obs, act)
                rules.layer_rewards(np.zeros(k), rules.compose())
                rules.tick()
            if attempt:
                best = min(best, (time.perf_counter() - start) / 500 * 1e6)
        print(f"| {k} | {best:.0f} | {best / k:.1f} |", flush=True)


if __name__ == "__main__":
    main()
