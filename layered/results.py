"""What a run writes of its results: the columns of its logs, mean losses per evaluation, the results of
the phases finished so far, and at the end results.json, results.md and the learning curves."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from layered.checkpoint import write_atomically
from layered.learners import LEARNERS
from layered.metrics import Evaluation
from layered.report import plot_curves, results_table
from layered.runstate import UpdateStats
from layered.schema import Recipe
from layered.summary import PHASES_FILE

EPISODE_FIELDS = ["phase", "step", "return", "length"]


def metrics_fields(recipe: Recipe) -> list[str]:
    """Columns of metrics.csv: every layer's, whether or not it is present in a phase; then each loss
    its learner names, per layer."""
    names = recipe.layer_names()
    losses = [f"{kind}_loss_{name}" for i, name in enumerate(names)
              for kind in LEARNERS.get(recipe.learner_config(i).kind).loss_names]
    return ["phase", "learn", "step", *Evaluation.columns(names), *losses]


def mean_losses(losses: dict[str, list[UpdateStats]], loss_names: Mapping[str, Sequence[str]]) -> dict[str, float]:
    """Each layer's mean of each of its learner's losses (`loss_names[layer]`) over the given updates (NaN
    where there are none)."""
    out = {}
    for name, stats in losses.items():
        for kind in loss_names[name]:
            values = [v for s in stats if (v := s[f"{kind}_loss"]) is not None]
            out[f"{kind}_loss_{name}"] = float(np.mean(values)) if values else float("nan")
    return out


def write_results(recipe: Recipe, rows: list[dict[str, Any]], out: Path, label: str) -> None:
    """results.json (every number of the table), results.md, and the learning-curve plot."""
    summary = {"env": recipe.env.id, "label": label, "seed": recipe.train.seed, "phases": rows}
    plot_curves(out / "metrics.csv", out / "curves.png", title=f"{recipe.env.id}: {label}, seed {recipe.train.seed}")
    write_atomically(out / "results.md", results_table(rows) + "\n")
    write_atomically(out / "results.json", json.dumps(summary, indent=2))  # last: it marks the run finished
    (out / PHASES_FILE).unlink(missing_ok=True)  # (results.json holds its rows now)


def write_finished_phases(rows: list[dict[str, Any]], out: Path) -> None:
    """The results rows of the phases finished so far, as results.json will hold them, so that a long run's
    finished phases can be reported before it ends (`layered report --unfinished`). Written whole each time:
    a phase finished again after a resume writes the same rows."""
    write_atomically(out / PHASES_FILE, json.dumps({"phases": rows}, indent=2))
