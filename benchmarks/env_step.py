"""Where a MuJoCo row's step goes: K environments of one Gymnasium task stepped one after another through
Gymnasium (as `layered.env_group` steps a group's rows), MuJoCo's own step of the same models alone (each
row's `mj_step` for the task's frame skip, no Python around it but the loop), Gymnasium's steps with the rows
split over Python threads (`--py-threads`: MuJoCo's step lets go of Python's lock, so the physics runs in
parallel and the rest takes turns; the same environments, so the same numbers), and `mujoco.rollout` stepping
all K states at once in MuJoCo's threads (`--threads`), in this process. Every way starts each timing from the
same K states and steps them with the same actions (episode ends are not acted on, so each way follows the
same trajectories); medians of `--repeats` timings of `--steps` steps each, the ways alternating. With
`--layered`, a group's own environments (`layered.env_workers.open_envs`) too, for each pair of `env.workers`
and `env.threads` given (and `env.wait`, after a second colon): the rows reset from the same seeds before each
timing, stepped with the same actions; with `--busy MS`, this process busy for MS milliseconds between asking
for each step and collecting it (as a group's update keeps it), so that a worker's hand-over shows as in training.

    python benchmarks/env_step.py                          # 32 Hopper-v5 rows; 2 Python threads; rollout 0, 1, 2
    python benchmarks/env_step.py --env Walker2d-v5 --rows 64 --py-threads 4,8,15 --threads 0,4,8,15
    python benchmarks/env_step.py --layered 0:0,0:2,1:0,1:2    # env.workers:env.threads
    python benchmarks/env_step.py --rows 4 --layered 0:0,1:0:sleep,1:0:spin --busy 0.3 --steps 2000 --repeats 5

A lead for lighter environment stepping, not a path the project takes yet: the rollout's states are not
Gymnasium's environments (no observations, rewards or episode ends are made from them here, and a rollout
does not carry MuJoCo's warm start from one step to the next, so its numbers are not Gymnasium's bit for bit).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import gymnasium as gym
import mujoco
import numpy as np
from mujoco import rollout

from layered.env_group import Envs
from layered.env_workers import open_envs


class Rows:
    """K environments of `env` at their first states, and `steps` random actions for each."""

    def __init__(self, env: str, rows: int, steps: int) -> None:
        self.envs = [gym.make(env, disable_env_checker=True) for _ in range(rows)]
        for k, one in enumerate(self.envs):
            one.reset(seed=k)
        first = self.envs[0].unwrapped
        self.model, self.skip = first.model, first.frame_skip  # type: ignore[attr-defined]
        self.datas = [one.unwrapped.data for one in self.envs]  # type: ignore[attr-defined]
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.states = np.zeros((rows, mujoco.mj_stateSize(self.model, self.spec)))
        for k, data in enumerate(self.datas):
            mujoco.mj_getState(self.model, data, self.states[k], self.spec)
        self.actions = np.random.default_rng(0).uniform(-1, 1, (steps, rows, self.model.nu))

    def restart(self) -> None:
        """Every row back at its first state."""
        for k, data in enumerate(self.datas):
            mujoco.mj_setState(self.model, data, self.states[k], self.spec)
            mujoco.mj_forward(self.model, data)

    def gymnasium(self) -> None:
        self.restart()
        for step in self.actions:
            for env, action in zip(self.envs, step, strict=True):
                env.step(action)

    def threaded(self, threads: int) -> Callable[[], None]:
        parts = [list(range(t, len(self.envs), threads)) for t in range(threads)]

        def run() -> None:
            self.restart()
            with ThreadPoolExecutor(threads) as pool:
                for step in self.actions:
                    list(pool.map(lambda part, step=step: [self.envs[k].step(step[k]) for k in part], parts))
        return run

    def mujoco(self) -> None:
        self.restart()
        for step in self.actions:
            for data, action in zip(self.datas, step, strict=True):
                data.ctrl[:] = action
                mujoco.mj_step(self.model, data, nstep=self.skip)

    def rollout(self, threads: int) -> Callable[[], None]:
        controls = np.repeat(self.actions[:, :, None, :], self.skip, axis=2)  # [steps, rows, skip, nu]

        def run() -> None:
            with rollout.Rollout(nthread=threads) as pool:
                scratch = [mujoco.MjData(self.model) for _ in range(max(threads, 1))]
                state = self.states
                for control in controls:
                    out, _ = pool.rollout(self.model, scratch, state, control, nstep=self.skip)
                    state = out[:, -1]
        return run

    def layered(self, envs: Envs, busy: float = 0.0) -> Callable[[], None]:
        """A group's environments stepped through the actions, this process busy for `busy` seconds in each step."""
        every = np.ones(len(self.envs), bool)

        def run() -> None:
            envs.reset(every, list(range(len(self.envs))))
            for step in self.actions:
                envs.step_async(step, every)
                until = time.perf_counter() + busy
                while time.perf_counter() < until:
                    pass
                envs.step_wait()
        return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--rows", type=int, default=32)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--py-threads", default="2", help="Python thread counts stepping Gymnasium's rows")
    parser.add_argument("--threads", default="0,1,2", help="rollout thread counts (0: on the calling thread)")
    parser.add_argument("--layered", default="",
                        help="env.workers:env.threads pairs of a group's environments, each with :env.wait if wanted")
    parser.add_argument("--busy", type=float, default=0.0, help="ms this process works between asking and collecting")
    args = parser.parse_args()
    rows = Rows(args.env, args.rows, args.steps)
    rows.actions = rows.actions.astype(np.float32)
    ways: dict[str, Callable[[], None]] = {"Gymnasium, one row after another": rows.gymnasium,
                                           "MuJoCo's step alone, one row after another": rows.mujoco}
    for threads in map(int, args.py_threads.split(",")):
        ways[f"Gymnasium, the rows split over {threads} Python threads"] = rows.threaded(threads)
    for threads in map(int, args.threads.split(",")):
        name = f"mujoco.rollout, {threads} threads" if threads else "mujoco.rollout, on the calling thread"
        ways[name] = rows.rollout(threads)
    opened: list[Envs] = []
    for pair in filter(None, args.layered.split(",")):
        workers, threads, *wait = pair.split(":")
        opened.append(open_envs(args.env, args.rows, int(workers), int(threads), wait=wait[0] if wait else "sleep"))
        name = f"a group's environments, env.workers {workers}, env.threads {threads}{''.join(f', {w}' for w in wait)}"
        ways[name + (f", busy {args.busy:g} ms" if args.busy else "")] = rows.layered(opened[-1], args.busy / 1e3)
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(args.repeats):
        for name, way in ways.items():
            start = time.perf_counter()
            way()
            times[name].append((time.perf_counter() - start) / args.steps)
    print(f"{args.rows} rows of {args.env} (frame skip {rows.skip}), {args.steps} steps, median of {args.repeats}\n")
    print("| way | ms per step of all rows | µs per row |\n|---|---|---|")
    for name, seconds in times.items():
        median = statistics.median(seconds)
        print(f"| {name} | {median * 1e3:.3f} | {median * 1e6 / args.rows:.1f} |")
    for env in rows.envs:
        env.close()
    for envs in opened:
        envs.close()


if __name__ == "__main__":
    main()
