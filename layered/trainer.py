"""The training loop: phases of a training order, each driving the stack's AEC env directly."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import torch
from tqdm import tqdm

from layered.agents import LayeredEnv, make_aec_env
from layered.buffer import Transition
from layered.checkpoint import load_checkpoint, save_checkpoint
from layered.envs import env_info
from layered.evaluate import evaluate
from layered.learners import LEARNERS, Learner
from layered.metrics import Evaluation, normalised_auc
from layered.orders import ORDERS, Phase
from layered.recipe import Recipe, learner_config, resolved
from layered.report import plot_curves, results_table


@dataclass(frozen=True)
class PhaseResult:
    """The outcome of one phase: its final evaluation and the AUC of its evaluation curve."""

    index: int
    phase: Phase
    steps: int
    final: Evaluation
    auc: float | None


def phases_of(recipe: Recipe) -> list[Phase]:
    """The phases of the recipe's training order."""
    return ORDERS.get(recipe.train.order)(recipe.layer_names(), recipe.train.phases or [])


def build_learners(recipe: Recipe, env: LayeredEnv) -> dict[str, Learner]:
    """One learner per layer, with its own seed; `env` must have every layer present."""
    learners = {}
    for i, layer in enumerate(recipe.layers):
        config = learner_config(recipe, i)
        seed = recipe.train.seed * 1000 + i
        learners[layer.name] = LEARNERS.get(config.kind)(
            env.observation_space(layer.name), env.action_space(layer.name), config, seed
        )
    return learners


def load_learners(recipe: Recipe, run_dir: Path) -> dict[str, Learner]:
    """The learners of a finished run, restored from its checkpoints."""
    env = make_aec_env(recipe)
    learners = build_learners(recipe, env)
    env.close()
    for name, learner in learners.items():
        learner.load_state_dict(load_checkpoint(run_dir / "checkpoints" / f"{name}.pt", name))
    return learners


class CsvLog:
    """Rows appended to a CSV file, flushed at once; the header is `fields` or the first row's keys."""

    def __init__(self, path: Path, fields: list[str] | None = None) -> None:
        self.path = path
        self._fields = fields
        if fields is not None:
            self._write_header()

    def _write_header(self) -> None:
        with self.path.open("w", newline="") as f:
            csv.DictWriter(f, fieldnames=self._fields or []).writeheader()

    def write(self, row: dict[str, Any]) -> None:
        if self._fields is None:
            self._fields = list(row)
            self._write_header()
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=self._fields, extrasaction="ignore", restval="").writerow(row)


def train(
    recipe: Recipe, out_dir: str | Path, max_steps: int | None = None, progress: bool = True,
    label: str | None = None,
) -> list[PhaseResult]:
    """Train every phase of `recipe`, writing the run directory; `max_steps` caps each phase.

    `label` names the setup for reports (e.g. `pendulum/tla-c`); runs of the same setup with
    different seeds share it. It defaults to the run directory's name.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.toml").write_text(tomli_w.dumps(resolved(recipe)))
    torch.manual_seed(recipe.train.seed)
    probe = make_aec_env(recipe)
    learners = build_learners(recipe, probe)
    probe.close()
    metrics = CsvLog(out / "metrics.csv")
    episodes = CsvLog(out / "episodes.csv", ["phase", "step", "return", "length"])
    results = []
    for p, phase in enumerate(phases_of(recipe)):
        budget = min(phase.steps or recipe.train.steps_per_phase, max_steps or np.iinfo(np.int64).max)
        result = run_phase(recipe, p, phase, budget, learners, metrics, episodes, progress)
        for name in phase.learn:
            save_checkpoint(out / "checkpoints" / f"{name}.pt", name, learners[name].state_dict())
        results.append(result)
    write_results(recipe, results, out, label or out.name)
    return results


def run_phase(
    recipe: Recipe, index: int, phase: Phase, budget: int, learners: dict[str, Learner],
    metrics: CsvLog, episodes: CsvLog, progress: bool,
) -> PhaseResult:
    """Train `phase.learn` for `budget` base steps with the other present layers frozen.

    The loop per decision: observe the layer's last transition, act, step the env, update.
    Learning layers act at random for their first `train.warmup` decisions, then with
    exploration noise, and update once per decision after that; frozen layers act greedily.
    """
    seed, gamma_mode = recipe.train.seed, recipe.train.discount
    env = make_aec_env(recipe, active=list(phase.active))
    eval_env = make_aec_env(recipe, active=list(phase.active), evaluation=True, record=True)
    eval_seed = seed + recipe.eval.seed_offset
    decisions = dict.fromkeys(phase.learn, 0)
    curve: list[tuple[int, Evaluation]] = []

    def evaluate_now(step: int) -> None:
        result = evaluate(eval_env, learners, recipe.eval.episodes, eval_seed)
        curve.append((step, result))
        metrics.write({"phase": index, "learn": "+".join(phase.learn), "step": step, **result.row()})
        bar.set_postfix_str(f"eval return {result.return_mean:.1f}")

    bar = tqdm(total=budget, desc=f"phase {index + 1}: {'+'.join(phase.learn)}", unit="step",
               disable=not progress, dynamic_ncols=True, mininterval=1.0)
    evaluate_now(0)
    steps, next_eval, episode = 0, recipe.eval.every, 0
    while steps < budget:
        env.reset(seed=seed + index if episode == 0 else None)
        pending: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for name in env.agent_iter():
            obs, reward, terminated, truncated, info = env.last()
            learner, learns = learners[name], name in decisions
            if learns and name in pending:
                gamma = learner.config.gamma
                discount = gamma ** info["elapsed"] if gamma_mode == "step" else gamma
                path = tuple(info.get("path", ()))
                learner.observe(Transition(*pending[name], reward, obs, terminated, discount, path))
            if terminated or truncated:
                env.step(None)
                continue
            if steps >= budget:
                break
            if not learns:
                action = learner.act(obs, explore=False)
            elif decisions[name] < recipe.train.warmup:
                action = learner.random_action()
            else:
                action = learner.act(obs, explore=True)
            pending[name] = (obs, action)
            before = env.episode_steps
            env.step(action)
            if learns:
                decisions[name] += 1
                if decisions[name] > recipe.train.warmup:
                    learner.update()
            advanced = env.episode_steps - before
            steps += advanced
            bar.update(advanced)
            if steps >= next_eval:
                evaluate_now(steps)
                next_eval += recipe.eval.every
        if not env.agents:  # the episode ran to its end rather than to the budget
            episodes.write({"phase": index, "step": steps, "return": env.episode_return, "length": env.episode_steps})
        episode += 1
    if curve[-1][0] != steps:
        evaluate_now(steps)
    bar.close()
    env.close()
    eval_env.close()
    return PhaseResult(index, phase, steps, curve[-1][1], _auc(recipe, curve))


def _auc(recipe: Recipe, curve: list[tuple[int, Evaluation]]) -> float | None:
    return_range = recipe.env.return_range or env_info(recipe.env.id).return_range
    if return_range is None:
        return None
    return normalised_auc([s for s, _ in curve], [e.return_mean for _, e in curve], return_range)


def write_results(recipe: Recipe, results: list[PhaseResult], out: Path, label: str) -> None:
    """results.json (every number of the table), results.md, and the learning-curve plot."""
    rows = [
        {
            "phase": r.index, "learn": list(r.phase.learn), "active": list(r.phase.active), "steps": r.steps,
            "auc": r.auc, **r.final.row(),
        }
        for r in results
    ]
    summary = {"env": recipe.env.id, "label": label, "seed": recipe.train.seed, "phases": rows}
    (out / "results.json").write_text(json.dumps(summary, indent=2))
    (out / "results.md").write_text(results_table(rows) + "\n")
    plot_curves(out / "metrics.csv", out / "curves.png", title=f"{recipe.env.id}: {out.name}")
