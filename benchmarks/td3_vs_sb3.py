"""TD3 training speed of `layered` against Stable-Baselines3, side by side on this machine.

Both train TD3 with the same hyperparameters (400-300 networks, batch 256, Adam 3e-4, one update
per environment step after the same random warm-up, policy delay 2, target noise 0.2 clipped at
0.5, exploration noise 0.1) on the same environments with the same torch thread count. Each run
is its own process; the two frameworks alternate, run by run, so that a machine's drift affects
both. Measured per run: training-phase environment steps per second (from the first gradient
update to the last, timed by wrapping each framework's update call), wall time of the whole
process and its peak memory (max RSS). Then, in one process: this machine's matrix-multiply rate
for the exact shapes of a TD3 update, and `layered`'s update time as a share of that floor.

    python benchmarks/td3_vs_sb3.py --quick          # ~2 min: Pendulum-v1, 1 repeat
    python benchmarks/td3_vs_sb3.py                  # Pendulum-v1 and Hopper-v5, 3 repeats each

Needs the optional extra: pip install 'layered[bench]' (Stable-Baselines3).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

HIDDEN = (400, 300)
BATCH = 256


def _set_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


class UpdateClock:
    """Wraps an update function: the times of its first and last calls, and how many there were."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.last = 0.0
        self.calls = 0

    def wrap(self, update: Any) -> Any:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self.first is None:
                self.first = time.perf_counter()
            out = update(*args, **kwargs)
            self.last = time.perf_counter()
            self.calls += 1
            return out
        return timed

    def steps_per_second(self) -> float:
        assert self.first is not None and self.calls > 1, "no updates were made: raise --steps above the warm-up"
        return (self.calls - 1) / (self.last - self.first)


def run_layered(env_id: str, steps: int, warmup: int, seed: int, precision: str = "float32") -> UpdateClock:
    import tempfile

    import layered
    from layered.learners.td3 import TD3

    clock = UpdateClock()
    TD3.update = clock.wrap(TD3.update)  # type: ignore[method-assign]
    recipe = layered.load_recipe({
        "env": {"id": env_id},
        "layers": [{"name": "td3", "period": 1}],
        "learner": {"kind": "td3", "hidden": list(HIDDEN), "batch_size": BATCH, "precision": precision},
        "train": {"steps_per_phase": steps, "warmup": warmup, "seed": seed},
        "eval": {"every": 10 * steps, "episodes": 1, "fresh_episodes": 0},
    })
    with tempfile.TemporaryDirectory() as out:
        layered.train(recipe, out, progress=False)
    return clock


def run_sb3(env_id: str, steps: int, warmup: int, seed: int) -> UpdateClock:
    import gymnasium as gym
    import numpy as np
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    env = gym.make(env_id)
    dims = env.action_space.shape[0]
    model = TD3(
        "MlpPolicy", env, learning_rate=3e-4, buffer_size=1_000_000, learning_starts=warmup, batch_size=BATCH,
        tau=0.005, gamma=0.99, train_freq=1, gradient_steps=1, policy_delay=2, target_policy_noise=0.2,
        target_noise_clip=0.5, action_noise=NormalActionNoise(np.zeros(dims), 0.1 * np.ones(dims)),
        policy_kwargs={"net_arch": list(HIDDEN)}, seed=seed, device="cpu", verbose=0,
    )
    clock = UpdateClock()
    model.train = clock.wrap(model.train)  # type: ignore[method-assign]
    model.learn(total_timesteps=steps)
    return clock


def child(framework: str, env_id: str, steps: int, warmup: int, threads: int, seed: int, precision: str) -> None:
    """One run; prints its measurements as one JSON line."""
    start = time.perf_counter()
    _set_threads(threads)
    if framework == "layered":
        clock = run_layered(env_id, steps, warmup, seed, precision)
    else:
        clock = run_sb3(env_id, steps, warmup, seed)
    print(json.dumps({
        "framework": framework, "env": env_id, "steps_per_second": clock.steps_per_second(),
        "updates": clock.calls, "wall_seconds": time.perf_counter() - start,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))


def mlp_matmuls(sizes: tuple[int, ...], backward: bool, input_grad: bool) -> list[tuple[int, int, int]]:
    """(m, k, n) of every matrix product of a forward pass of an MLP on a batch (and of its backward)."""
    shapes = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        shapes.append((BATCH, a, b))  # forward
        if backward:
            shapes.append((b, BATCH, a))  # weight gradient
            if i > 0 or input_grad:
                shapes.append((BATCH, b, a))  # input gradient
    return shapes


def update_matmuls(obs_dim: int, act_dim: int) -> tuple[list[tuple[int, int, int]], list[tuple[int, int, int]]]:
    """Matrix products of a critic update (every update) and of an actor update (every second one)."""
    actor, critic = (obs_dim, *HIDDEN, act_dim), (obs_dim + act_dim, *HIDDEN, 1)
    critic_step = mlp_matmuls(actor, False, False) + 2 * mlp_matmuls(critic, False, False)  # targets
    critic_step += 2 * mlp_matmuls(critic, True, False)
    actor_step = mlp_matmuls(actor, True, False) + mlp_matmuls(critic, True, True)
    return critic_step, actor_step


def floor(env_id: str, threads: int) -> dict[str, float]:
    """This machine's matmul time for one TD3 update's products, against layered's measured update."""
    import gymnasium as gym
    import numpy as np
    import torch

    from layered.buffer import Transition
    from layered.learners.td3 import TD3, TD3Config
    from layered.outputs import OutputLayout

    _set_threads(threads)
    env = gym.make(env_id)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    critic_step, actor_step = update_matmuls(obs_dim, act_dim)

    def product_seconds(m: int, k: int, n: int) -> float:
        a, b = torch.randn(m, k), torch.randn(k, n)
        for _ in range(20):
            torch.mm(a, b)
        reps, start = 200, time.perf_counter()
        for _ in range(reps):
            torch.mm(a, b)
        return (time.perf_counter() - start) / reps

    cost = {shape: product_seconds(*shape) for shape in set(critic_step + actor_step)}
    floor_s = sum(cost[s] for s in critic_step) + sum(cost[s] for s in actor_step) / 2
    flops = sum(2 * m * k * n for m, k, n in critic_step) + sum(2 * m * k * n for m, k, n in actor_step) / 2
    box = env.action_space
    learner = TD3(env.observation_space, box, OutputLayout(act_dim), TD3Config(), seed=0)
    rng = np.random.default_rng(0)
    for _ in range(5000):
        o = rng.standard_normal(obs_dim).astype(np.float32)
        learner.observe(Transition(o, learner.random_action(), float(rng.normal()), o, False, 0.99))
    for _ in range(50):
        learner.update()
    reps, start = 400, time.perf_counter()
    for _ in range(reps):
        learner.update()
    update_s = (time.perf_counter() - start) / reps
    obs = np.zeros(obs_dim, np.float32)
    acts, start = 2000, time.perf_counter()
    for _ in range(acts):
        learner.act(obs, explore=True)
    act_s = (time.perf_counter() - start) / acts
    return {"update_ms": 1e3 * update_s, "floor_ms": 1e3 * floor_s, "gflop": flops / 1e9,
            "gflops_per_s": flops / floor_s / 1e9, "share_of_floor": floor_s / update_s, "act_us": 1e6 * act_s}


LATENCY_STACKS = ["pendulum/td3.toml", "pendulum/tla-c.toml", "research/pendulum-residual-3.toml",
                  "hopper/tla-realtime.toml", "research/hopper-residual-3.toml"]


def latency(recipe_name: str, threads: int, steps: int = 4000) -> dict[str, Any]:
    """Time per base step from observation to executed action (the environment's step excluded) of
    a stack with untrained networks of the recipe's sizes: in the library, as `layered eval` acts,
    and exported with `layered export` (TorchScript, and ONNX where onnxruntime is installed); the
    same measurement as `layered export` prints."""
    import importlib.util
    import tempfile
    from pathlib import Path

    import layered
    from layered.export import export_stack
    from layered.latency import compare
    from layered.learner_set import build_learners
    from layered.orders import phases_of

    _set_threads(threads)
    recipes = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "recipes")
    recipe = layered.load_recipe(os.path.join(recipes, recipe_name))
    learners = build_learners(recipe)
    active = list(phases_of(recipe)[-1].active)
    backends = ["torchscript"] + (["onnx"] if importlib.util.find_spec("onnxruntime") else [])
    out: dict[str, Any] = {"layers": len(active), "env": recipe.env.id}
    with tempfile.TemporaryDirectory() as folder:
        for backend in backends:
            exported = export_stack(recipe, learners, active, Path(folder) / backend, backend)
            result = compare(recipe, learners, active, exported, 1, 0, min_steps=steps)
            out["library"] = result.library.__dict__
            out[backend] = {**result.exported.__dict__, "max_difference": result.max_difference}
    return out


def spawn(args: list[str], threads: int) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"benchmark run {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="Pendulum-v1 only, one repeat, 3000 steps")
    parser.add_argument("--envs", default="Pendulum-v1,Hopper-v5", help="comma-separated Gymnasium ids")
    parser.add_argument("--steps", type=int, default=6000, help="environment steps per run (default 6000)")
    parser.add_argument("--warmup", type=int, default=1000, help="random steps before updates (default 1000)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per framework and environment (default 3)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of every run (default 1)")
    parser.add_argument("--precision", choices=["float32", "bfloat16"], default="float32",
                        help="layered's learner.precision (SB3 runs in float32; default float32)")
    parser.add_argument("--sections", default="training,floor,latency",
                        help="which parts to run, comma-separated (default training,floor,latency)")
    parser.add_argument("--child", nargs=7, help=argparse.SUPPRESS)
    parser.add_argument("--floor", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--latency", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        framework, env_id, steps, warmup, threads, seed, precision = args.child
        child(framework, env_id, int(steps), int(warmup), int(threads), int(seed), precision)
        return
    if args.floor:
        print(json.dumps(floor(args.floor[0], int(args.floor[1]))))
        return
    if args.latency:
        print(json.dumps(latency(args.latency[0], int(args.latency[1]))))
        return
    envs = ["Pendulum-v1"] if args.quick else args.envs.split(",")
    steps, repeats = (3000, 1) if args.quick else (args.steps, args.repeats)
    sections = args.sections.split(",")
    if "training" in sections:
        training(envs, steps, repeats, args)
    if "floor" in sections:
        floors(envs, args.threads)
    if "latency" in sections:
        latencies(args.threads)


def training(envs: list[str], steps: int, repeats: int, args: argparse.Namespace) -> None:
    """Training-phase steps/s, wall time and peak memory of both frameworks, alternating run by run."""
    print(f"TD3, layered ({args.precision} updates) against Stable-Baselines3: {steps} steps per run "
          f"({args.warmup} random), {repeats} run(s) each, {args.threads} torch thread(s), {os.cpu_count()} cores")
    results: list[dict[str, Any]] = []
    for env_id in envs:
        for r in range(repeats):
            order = ["layered", "sb3"] if r % 2 == 0 else ["sb3", "layered"]
            for framework in order:
                row = spawn(["--child", framework, env_id, str(steps), str(args.warmup), str(args.threads), str(r),
                             args.precision], args.threads)
                results.append(row)
                print(f"  {env_id:<14} {framework:<8} {row['steps_per_second']:7.1f} steps/s  "
                      f"wall {row['wall_seconds']:6.1f} s  peak {row['peak_mib']:6.0f} MiB", flush=True)
    print("\n| environment | layered steps/s | SB3 steps/s | ratio | layered wall s | SB3 wall s "
          "| layered peak MiB | SB3 peak MiB |")
    print("|---|---|---|---|---|---|---|---|")
    for env_id in envs:
        med = {fw: {k: statistics.median(r[k] for r in results if r["env"] == env_id and r["framework"] == fw)
                    for k in ("steps_per_second", "wall_seconds", "peak_mib")} for fw in ("layered", "sb3")}
        ratio = med["layered"]["steps_per_second"] / med["sb3"]["steps_per_second"]
        print(f"| {env_id} | {med['layered']['steps_per_second']:.1f} | {med['sb3']['steps_per_second']:.1f} "
              f"| {ratio:.2f}x | {med['layered']['wall_seconds']:.1f} | {med['sb3']['wall_seconds']:.1f} "
              f"| {med['layered']['peak_mib']:.0f} | {med['sb3']['peak_mib']:.0f} |")


def floors(envs: list[str], threads: int) -> None:
    """layered's update time against this machine's matrix-multiply floor, and one act call."""
    print("\n| environment | update ms | matmul floor ms | GFLOP / update | GEMM GFLOP/s | share of floor "
          "| act µs |")
    print("|---|---|---|---|---|---|---|")
    for env_id in envs:
        f = spawn(["--floor", env_id, str(threads)], threads)
        print(f"| {env_id} | {f['update_ms']:.2f} | {f['floor_ms']:.2f} | {f['gflop']:.3f} "
              f"| {f['gflops_per_s']:.0f} | {f['share_of_floor']:.0%} | {f['act_us']:.0f} |")


def latencies(threads: int) -> None:
    """Decision latency of 1- to 3-layer stacks, in the library and exported."""
    print("\nDecision latency: time per base step from observation to executed action, environment step "
          "excluded, untrained networks of each recipe's sizes (median / p99 µs):")
    print("| recipe | environment | layers | library | exported TorchScript | exported ONNX |")
    print("|---|---|---|---|---|---|")
    for name in LATENCY_STACKS:
        lat = spawn(["--latency", name, str(threads)], threads)
        cells = [f"{lat[k]['median_us']:.0f} / {lat[k]['p99_us']:.0f}" if k in lat else "n/a"
                 for k in ("library", "torchscript", "onnx")]
        print(f"| {name} | {lat['env']} | {lat['layers']} | {' | '.join(cells)} |")

if __name__ == "__main__":
    main()
