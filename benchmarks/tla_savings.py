"""What a layered stack saves: the wall time of whole TLA-C and TLA-O runs against one TD3 run at the
paper's Pendulum budget, and the network evaluations per episode that slow layers and committed
gates avoid.

    python benchmarks/tla_savings.py                 # the paper's budget: about 25 minutes on one core
    python benchmarks/tla_savings.py --steps 6000    # a quicker look (warm-up then weighs more)

Each recipe trains in its own process with one torch thread (`layered train --threads 1`), one
after the other; the numbers per episode come from each run's results.json (its final evaluation).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RECIPES = {"td3": "pendulum/td3.toml", "tla-c": "pendulum/tla-c.toml", "tla-o": "pendulum/tla-o.toml"}
ROOT = Path(__file__).resolve().parent.parent


def train(recipe: str, out: Path, steps: int | None, seed: int) -> dict[str, float]:
    """Wall time of one whole run (every phase, evaluations included) and its last phase's final evaluation."""
    command = [sys.executable, "-m", "layered.cli", "train", str(ROOT / "recipes" / recipe), "--out", str(out),
               "--threads", "1", "--seed", str(seed), *(["--steps", str(steps)] if steps else [])]
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    wall = time.perf_counter() - start
    phases = json.loads((out / "results.json").read_text())["phases"]
    final = phases[-1]
    return {"wall_s": wall, "steps": sum(p["steps"] for p in phases), "decisions": final["decisions"],
            "episode_steps": final["episode_steps"], "compute": final["compute"], "return": final["return_mean"],
            **{k: v for k, v in final.items() if k.startswith("decided_")}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, help="cap every phase at N steps (default: the recipes' 30 000)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, recipe in RECIPES.items():
            rows[name] = train(recipe, Path(folder) / name, args.steps, args.seed)
            print(f"  {name:<6} {rows[name]['wall_s']:7.1f} s for {rows[name]['steps']} steps", flush=True)
    td3 = rows["td3"]
    print("\n| setup | environment steps | wall s | wall / TD3 | network evaluations per episode (per layer) "
          "| MACs per episode | MACs / TD3 | return |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        per_layer = ", ".join(f"{k.removeprefix('decided_')} {v * r['episode_steps']:.0f}"
                              for k, v in r.items() if k.startswith("decided_"))
        print(f"| {name} | {r['steps']} | {r['wall_s']:.1f} | {r['wall_s'] / td3['wall_s']:.2f}x | {per_layer} "
              f"| {r['compute']:.3g} | {r['compute'] / td3['compute']:.2f}x | {r['return']:.1f} |")


if __name__ == "__main__":
    main()
