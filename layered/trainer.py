"""The training loop: phases of a training order, each driving the stack's AEC env directly."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import torch
from tqdm import tqdm

from layered.agents import make_aec_env
from layered.buffer import Transition
from layered.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from layered.envs import env_info
from layered.evaluate import evaluate
from layered.learners import LEARNERS, Learner, UpdateStats
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


def build_learners(recipe: Recipe) -> dict[str, Learner]:
    """One new learner per layer, each with its own seed, on the spaces of the whole stack."""
    env = make_aec_env(recipe)
    learners = {}
    for i, layer in enumerate(recipe.layers):
        config = learner_config(recipe, i)
        seed = recipe.train.seed * 1000 + i
        learners[layer.name] = LEARNERS.get(config.kind)(
            env.observation_space(layer.name), env.action_space(layer.name), config, seed
        )
    env.close()
    return learners


def load_learners(recipe: Recipe, run_dir: Path) -> dict[str, Learner]:
    """The learners of a finished run, restored from its checkpoints."""
    learners = build_learners(recipe)
    for name, learner in learners.items():
        learner.load_state_dict(load_checkpoint(run_dir / "checkpoints" / f"{name}.pt", name))
    return learners


class CsvLog:
    """Rows appended to a CSV file, flushed at once; the header is `fields` or the first row's keys.

    With `keep_phases_below = k` an existing file keeps its rows of phases before k (resuming).
    """

    def __init__(self, path: Path, fields: list[str] | None = None, keep_phases_below: int = 0) -> None:
        self.path = path
        self._fields = fields
        kept: list[dict[str, str]] = []
        if keep_phases_below and path.exists():
            with path.open() as f:
                reader = csv.DictReader(f)
                self._fields = list(reader.fieldnames or []) or fields
                kept = [row for row in reader if int(row["phase"]) < keep_phases_below]
        if self._fields is not None:
            self._write_header()
            for row in kept:
                self.write(row)

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
    label: str | None = None, resume: bool = False, plugins: Sequence[str] = (),
) -> list[dict[str, Any]]:
    """Train every phase of `recipe`, writing the run directory; `max_steps` caps each phase.

    `label` names the setup for reports (e.g. `pendulum/tla-c`); runs of the same setup with
    different seeds share it. It defaults to the run directory's name. After each phase the
    whole training state is saved; with `resume`, a run that was stopped continues from its
    last finished phase and ends exactly as if it had never stopped. `plugins` (see
    layered.plugins) are recorded so that evaluating the run imports them again.
    Returns the results row of each phase, as in results.json.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.toml").write_text(tomli_w.dumps(resolved(recipe)))
    if plugins:
        (out / "plugins.json").write_text(json.dumps(list(plugins)))
    torch.manual_seed(recipe.train.seed)
    learners = build_learners(recipe)
    run_state = out / "checkpoints" / "run.pt"
    rows: list[dict[str, Any]] = []
    if resume and run_state.exists():
        rows = _restore(run_state, learners, max_steps)
    metrics = CsvLog(out / "metrics.csv", keep_phases_below=len(rows))
    episodes = CsvLog(out / "episodes.csv", ["phase", "step", "return", "length"], keep_phases_below=len(rows))
    for p, phase in enumerate(phases_of(recipe)):
        if p < len(rows):
            continue
        budget = min(phase.steps or recipe.train.steps_per_phase, max_steps or np.iinfo(np.int64).max)
        result = run_phase(recipe, p, phase, budget, learners, metrics, episodes, progress)
        for name in phase.learn:
            save_checkpoint(out / "checkpoints" / f"{name}.pt", name, learners[name].state_dict())
        rows.append(phase_row(result))
        save_checkpoint(run_state, "run", {
            "rows": json.dumps(rows), "max_steps": max_steps, "torch_rng": torch.get_rng_state(),
            "learners": {name: learner.resume_state() for name, learner in learners.items()},
        })
    write_results(recipe, rows, out, label or out.name)
    return rows


def run_plugins(run_dir: Path) -> list[str]:
    """The plugins a run was trained with."""
    path = run_dir / "plugins.json"
    return list(json.loads(path.read_text())) if path.exists() else []


def _restore(run_state: Path, learners: dict[str, Learner], max_steps: int | None) -> list[dict[str, Any]]:
    """Load the saved training state into `learners`; the finished phases' results rows."""
    state = load_checkpoint(run_state, "run")
    if state["max_steps"] != max_steps:
        raise CheckpointError(f"{run_state}: the run was started with --steps {state['max_steps']}, not {max_steps}")
    for name, learner in learners.items():
        learner.load_resume_state(state["learners"][name])
    torch.set_rng_state(state["torch_rng"])
    return list(json.loads(state["rows"]))


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

    losses: dict[str, list[UpdateStats]] = {name: [] for name in phase.learn}

    def evaluate_now(step: int) -> None:
        result = evaluate(eval_env, learners, recipe.eval.episodes, eval_seed)
        curve.append((step, result))
        metrics.write({"phase": index, "learn": "+".join(phase.learn), "step": step, **result.row(),
                       **_mean_losses(losses)})
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
                if decisions[name] > recipe.train.warmup and (stats := learner.update()) is not None:
                    losses[name].append(stats)
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


def _mean_losses(losses: dict[str, list[UpdateStats]]) -> dict[str, float]:
    """Mean critic and actor loss of each learning layer since the last call (NaN if none); clears them."""
    out = {}
    for name, stats in losses.items():
        actor = [s.actor_loss for s in stats if s.actor_loss is not None]
        out[f"critic_loss_{name}"] = float(np.mean([s.critic_loss for s in stats])) if stats else float("nan")
        out[f"actor_loss_{name}"] = float(np.mean(actor)) if actor else float("nan")
        stats.clear()
    return out


def _auc(recipe: Recipe, curve: list[tuple[int, Evaluation]]) -> float | None:
    return_range = recipe.env.return_range or env_info(recipe.env.id).return_range
    if return_range is None:
        return None
    return normalised_auc([s for s, _ in curve], [e.return_mean for _, e in curve], return_range)


def phase_row(r: PhaseResult) -> dict[str, Any]:
    """A phase's results as one flat row of results.json."""
    return {
        "phase": r.index, "learn": list(r.phase.learn), "active": list(r.phase.active), "steps": r.steps,
        "auc": r.auc, **r.final.row(),
    }


def write_results(recipe: Recipe, rows: list[dict[str, Any]], out: Path, label: str) -> None:
    """results.json (every number of the table), results.md, and the learning-curve plot."""
    summary = {"env": recipe.env.id, "label": label, "seed": recipe.train.seed, "phases": rows}
    (out / "results.json").write_text(json.dumps(summary, indent=2))
    (out / "results.md").write_text(results_table(rows) + "\n")
    plot_curves(out / "metrics.csv", out / "curves.png", title=f"{recipe.env.id}: {out.name}")
