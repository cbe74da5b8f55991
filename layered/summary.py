"""Reading finished run directories and aggregating the runs of one setup over seeds."""

from __future__ import annotations

import csv
import json
import re
import sys
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# The paper's methods first, in its column order; any other setup follows alphabetically.
METHOD_ORDER = ["td3", "temporl", "tla-o", "tla-c", "td3-realtime", "tla-realtime"]


@dataclass(frozen=True)
class FinishedRun:
    """One finished run: its setup, seed, final evaluation, and its evaluation curves over the last
    phase and over the whole run (environment steps counted from the start of training)."""

    path: Path
    env: str
    label: str
    seed: int
    realtime: bool
    final: dict[str, float]
    curve: tuple[tuple[int, float], ...]
    total_curve: tuple[tuple[int, float], ...] = ()
    phase_starts: tuple[int, ...] = ()  # steps since training began at which phases 1, 2, ... started
    phases: tuple[dict[str, Any], ...] = ()  # each phase's results as `results.json` holds them, the last = `final`

    @property
    def method(self) -> str:
        return self.label.rsplit("/", 1)[-1]


class BrokenRun(ValueError):
    """A run directory whose results cannot be read; the message names it and what is wrong."""


def load_finished_run(path: Path) -> FinishedRun:
    """The run in directory `path`; raises FileNotFoundError naming what is missing, BrokenRun naming
    what cannot be read."""
    results_file = path / "results.json"
    if not results_file.exists():
        raise FileNotFoundError(f"{path} is not a finished run (no results.json)")
    try:
        return _read_finished_run(path, results_file)
    except (OSError, ValueError, KeyError, IndexError, TypeError, tomllib.TOMLDecodeError) as e:
        raise BrokenRun(f"{path}: its results cannot be read ({e.__class__.__name__}: {e})") from None


def _read_finished_run(path: Path, results_file: Path) -> FinishedRun:
    results = json.loads(results_file.read_text())
    recipe = tomllib.loads((path / "recipe.toml").read_text())
    final = results["phases"][-1]
    last_phase = str(final["phase"])
    with (path / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    curve = tuple((int(r["step"]), float(r["return_mean"])) for r in rows if r["phase"] == last_phase)
    label = results.get("label") or re.sub(r"-s\d+(-\d{8}-\d{6})?$", "", path.name)
    return FinishedRun(
        path=path, env=results["env"], label=label, seed=int(results.get("seed", recipe["train"]["seed"])),
        realtime=any(layer.get("delay", 0) > 0 for layer in recipe["layers"]),
        final={k: v for k, v in final.items() if isinstance(v, int | float) and not isinstance(v, bool)},
        curve=curve, total_curve=_total_curve(rows), phase_starts=_phase_starts(rows),
        phases=tuple(results["phases"]),
    )


def _total_curve(rows: Sequence[dict[str, str]]) -> tuple[tuple[int, float], ...]:
    """Evaluation return against environment steps since training began, phases laid end to end.

    A later phase's first evaluation is dropped: it falls on the step where the previous phase
    ended, and the curve shows the stack as trained at each step."""
    points: list[tuple[int, float]] = []
    offset = 0
    for phase in dict.fromkeys(r["phase"] for r in rows):
        steps = [(int(r["step"]), float(r["return_mean"])) for r in rows if r["phase"] == phase]
        points += [(offset + s, v) for s, v in steps if not (points and s == 0)]
        offset += max(s for s, _ in steps)
    return tuple(points)


def _phase_starts(rows: Sequence[dict[str, str]]) -> tuple[int, ...]:
    """The steps since training began at which each phase after the first started."""
    phases = dict.fromkeys(r["phase"] for r in rows)
    ends = [max(int(r["step"]) for r in rows if r["phase"] == phase) for phase in phases]
    return tuple(int(x) for x in np.cumsum(ends)[:-1])


@dataclass(frozen=True)
class Setup:
    """The runs of one (environment, method) pair, one per seed; the method is the recipe's name."""

    env: str
    label: str
    runs: tuple[FinishedRun, ...]

    @property
    def method(self) -> str:
        return self.runs[0].method

    @property
    def realtime(self) -> bool:
        return self.runs[0].realtime

    def stat(self, key: str) -> tuple[float, float]:
        """Mean and standard deviation over seeds of a final-evaluation value (NaN if absent)."""
        values = np.array([r.final.get(key, np.nan) for r in self.runs], np.float64)
        return float(np.mean(values)), float(np.std(values))

    def curve(self, whole_run: bool = False) -> tuple[np.ndarray, ...]:
        """Steps, mean, std, lowest and highest over seeds of the evaluation return, over the last
        phase or the whole run.

        Runs are aligned evaluation by evaluation, up to the fewest any run made, at the mean of their
        steps: a slow layer evaluates on its first decision after the schedule, a step or two apart
        between seeds."""
        curves = [r.total_curve if whole_run else r.curve for r in self.runs]
        n = min(len(c) for c in curves)
        points = np.array([c[:n] for c in curves], np.float64).reshape(len(curves), n, 2)
        returns = points[:, :, 1]
        return points[:, :, 0].mean(axis=0), returns.mean(axis=0), returns.std(axis=0), returns.min(axis=0), \
            returns.max(axis=0)


def group(runs: Iterable[FinishedRun]) -> list[Setup]:
    """Runs grouped by (environment, method), in the paper's method order."""
    by_key: dict[tuple[str, str], list[FinishedRun]] = {}
    for run in runs:
        by_key.setdefault((run.env, run.method), []).append(run)
    setups = [Setup(env, rs[0].label, tuple(sorted(rs, key=lambda r: r.seed))) for (env, _), rs in by_key.items()]

    def order(s: Setup) -> tuple[str, int, str]:
        rank = METHOD_ORDER.index(s.method) if s.method in METHOD_ORDER else len(METHOD_ORDER)
        return (s.env, rank, s.label)

    return sorted(setups, key=order)


def find_runs(paths: Sequence[Path]) -> list[FinishedRun]:
    """Every finished run in `paths`, each a run directory or a folder holding run directories."""
    found: list[FinishedRun] = []
    for path in paths:
        dirs = [path] if (path / "results.json").exists() else sorted(p.parent for p in path.rglob("results.json"))
        if not dirs:
            raise FileNotFoundError(f"{path}: no finished runs (no results.json) in it")
        for d in dirs:
            try:
                found.append(load_finished_run(d))
            except BrokenRun as e:
                print(f"layered: warning: {e}; reporting the other runs", file=sys.stderr)
    if not found:
        raise FileNotFoundError(f"no readable finished run in {', '.join(map(str, paths))}")
    return found
