"""Reading run directories (finished ones, and where asked those still training or stopped before their end)
and aggregating the runs of one setup over seeds."""

from __future__ import annotations

import csv
import json
import re
import sys
import tomllib
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from layered.metrics import best_evaluation
from layered.progress import count

PHASES_FILE = "phases.json"  # an unfinished run's finished phases, as results.json will hold them

# The paper's methods first, in its column order; any other setup follows alphabetically.
METHOD_ORDER = ["td3", "temporl", "tla-o", "tla-c", "td3-realtime", "tla-realtime"]


@dataclass(frozen=True)
class Run:
    """One run: its setup, seed, final evaluation, and its evaluation curves over the last phase and over
    the whole run (environment steps counted from the start of training). A run not finished (still training,
    or stopped before its end) is taken at its last evaluation, and `stands` says where that was."""

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
    stands: str = ""  # where an unfinished run's last evaluation was ("phase 0, step 75000"); "" once finished
    setting: tuple[tuple[str, str], ...] = ()  # its resolved recipe as (dotted key, value) pairs (`_setting`)
    unnamed: tuple[str, ...] = ()  # the `key=value`s that set its setup apart but its label leaves out (`told_apart`)
    trained_before: int = 0  # steps of training behind the weights its layers started from (`_start_weights`)
    started_from: frozenset[Path] = frozenset()  # the run directories behind those weights, resolved
    continues: tuple[Path, int] | None = None  # the run (resolved) and phase at whose end all of them were saved

    @property
    def finished(self) -> bool:
        """Whether the run trained to its end (it has no standing: its results are written)."""
        return not self.stands

    @property
    def method(self) -> str:
        """The recipe's name (with the settings `told_apart` adds to the label); an unfinished run's is marked, so
        that it forms a setup of its own."""
        recipe, _, settings = self.label.partition(" ")
        name = recipe.rsplit("/", 1)[-1] + (f" {settings}" if settings else "")
        return name if self.finished else f"{name} (unfinished)"

    def shares_layers_with(self, other: Run) -> bool:
        """Whether the two runs hold trained layers in common: one started from the other's weights, or both from
        one run's. Their returns are then not independent samples (as two seeds' are) but a pair."""
        mine, theirs = self.path.resolve(), other.path.resolve()
        return mine in other.started_from or theirs in self.started_from or bool(self.started_from & other.started_from)


class BrokenRun(ValueError):
    """A run directory whose results cannot be read; the message names it and what is wrong."""


def load_finished_run(path: Path) -> Run:
    """The finished run in directory `path`; raises FileNotFoundError naming what is missing, BrokenRun naming
    what cannot be read."""
    results_file = path / "results.json"
    if not results_file.exists():
        raise FileNotFoundError(f"{path} is not a finished run (no results.json)")
    return _readable(path, _read_finished_run)


def load_unfinished_run(path: Path) -> Run:
    """The run in directory `path` that has not finished (no results.json), at its last evaluation in
    metrics.csv, with the results of the phases before it that have finished (phases.json); raises BrokenRun
    where it cannot be read or has not evaluated yet."""
    return _readable(path, _read_unfinished_run)


def _readable(path: Path, read: Callable[[Path], Run]) -> Run:
    """`read(path)`, what makes its files unreadable raised as BrokenRun naming the run."""
    try:
        return read(path)
    except (OSError, ValueError, KeyError, IndexError, TypeError, tomllib.TOMLDecodeError) as e:
        raise BrokenRun(f"{path}: its results cannot be read ({e.__class__.__name__}: {e})") from None


def _read_finished_run(path: Path) -> Run:
    results = json.loads((path / "results.json").read_text())
    info = _run_json(path)
    recipe = _recipe(path, info)
    final = results["phases"][-1]
    rows = _metrics(path)
    start = _start_weights(recipe)
    return Run(
        path=path, env=results["env"], label=results.get("label") or _label(path),
        seed=int(results.get("seed", recipe["train"]["seed"])), realtime=_realtime(recipe),
        final={k: v for k, v in final.items() if isinstance(v, int | float) and not isinstance(v, bool)}
        | _run_auc(results["phases"], recipe, _continues(start[2])),
        curve=_curve(rows, str(final["phase"])), phases=tuple(results["phases"]), setting=_setting(recipe, info),
        **_whole_run(rows, start),
    )


def _run_json(path: Path) -> dict[str, Any]:
    """A run's run.json (empty where an older run has none)."""
    return json.loads((path / "run.json").read_text()) if (path / "run.json").exists() else {}


def _recipe(path: Path, info: dict[str, Any]) -> dict[str, Any]:
    """A run's resolved recipe, each layer's `learner.precision = "auto"` replaced by what it computed in (its
    run.json's `precision`, `info`, where recorded): runs of one recipe on machines with and without bfloat16 are
    different setups."""
    recipe = tomllib.loads((path / "recipe.toml").read_text())
    for layer in recipe.get("layers", []):
        learner = layer.get("learner", {})
        if learner.get("precision") == "auto" and layer.get("name") in info.get("precision", {}):
            learner["precision"] = info["precision"][layer["name"]]
    return recipe


def _read_unfinished_run(path: Path) -> Run:
    info = _run_json(path)
    recipe = _recipe(path, info)
    rows = _metrics(path)
    if not rows:
        raise ValueError("metrics.csv has no evaluation yet")
    last = rows[-1]
    final = {k: float(v) for k, v in last.items() if k not in ("phase", "learn") and v}
    final["phase"] = int(last["phase"])
    curve = _curve(rows, last["phase"])
    final["best_step"], final["best_return_mean"] = curve[best_evaluation([r for _, r in curve])]  # (so far)
    finished = json.loads((path / PHASES_FILE).read_text())["phases"] if (path / PHASES_FILE).exists() else []
    before = tuple(row for row in finished if row["phase"] < final["phase"])
    return Run(
        path=path, env=recipe["env"]["id"], label=info.get("label") or _label(path), seed=int(recipe["train"]["seed"]),
        realtime=_realtime(recipe), final=final, curve=curve,
        phases=(*before, {**final, "learn": last["learn"].split("+")}),
        stands=f"phase {last['phase']}, step {last['step']}", setting=_setting(recipe, info),
        **_whole_run(rows, _start_weights(recipe)),
    )


def _run_auc(phases: Sequence[dict[str, Any]], recipe: dict[str, Any], end: _End | None) -> dict[str, float]:
    """`run_auc`, the normalised AUC over all of a run's training steps: its phases' AUCs weighted by their steps
    (their curves laid end to end), comparable between setups that train in different phases. Where its layers
    started from weights, the phases behind the stack it continues (`end`) come first, as on the whole-run curve;
    none where those are not known, or where a phase has no AUC (no return range)."""
    if any(layer.get("weights") for layer in recipe["layers"]):
        if end is None or end.behind is None:
            return {}
        phases = [*end.behind, *phases]
    if not phases or not all(isinstance(p.get("auc"), int | float) and p.get("steps") for p in phases):
        return {}
    return {"run_auc": sum(p["auc"] * p["steps"] for p in phases) / sum(p["steps"] for p in phases)}


NOT_A_SETTING = frozenset({"train.seed", "train.checkpoint_every", "env.workers", "env.threads", "log"})
"""Recipe keys that differ between the seeds of one setup, or change no number it reports."""


def _setting(recipe: dict[str, Any], info: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    """A resolved recipe as (dotted key, value) pairs, layers by name, `NOT_A_SETTING` left out and
    `train.steps_per_phase` too where explicit phases each name their steps (there it changes nothing, and a label
    that showed it would misstate the budget), with the `--steps` cap of its run.json (`info`) as `--steps`: what
    tells the setups of runs filed under one label apart; and `trained` as a seed of a `group` or `alone` (a seed's
    numbers depend on whether, and with which seeds, it trained as a group)."""
    train = recipe.get("train", {})
    phases = train.get("phases") or []
    if train.get("order") == "explicit" and phases and all(p.get("steps") for p in phases):
        recipe = {**recipe, "train": {k: v for k, v in train.items() if k != "steps_per_phase"}}
    cap = (("--steps", "none" if info["max_steps"] is None else str(info["max_steps"])),) if "max_steps" in info else ()
    return _pairs(recipe) + cap + (("trained", "group" if info.get("group") else "alone"),)


def _pairs(recipe: Any, prefix: str = "") -> tuple[tuple[str, str], ...]:
    """`recipe` flattened to (dotted key, value) pairs below `prefix`, lists of named tables by name."""
    if isinstance(recipe, list) and recipe and all(isinstance(v, dict) and "name" in v for v in recipe):
        recipe = {v["name"]: {k: x for k, x in v.items() if k != "name"} for v in recipe}
    if isinstance(recipe, dict):
        return tuple(pair for k, v in recipe.items() if f"{prefix}{k}" not in NOT_A_SETTING
                     for pair in _pairs(v, f"{prefix}{k}."))
    return ((prefix[:-1], recipe if isinstance(recipe, str) else json.dumps(recipe, sort_keys=True)),)


def _metrics(path: Path) -> list[dict[str, str]]:
    with (path / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def _label(path: Path) -> str:
    """The setup of a run that does not name it: its directory's name without the seed and time."""
    return re.sub(r"-s\d+(-\d{8}-\d{6})?$", "", path.name)


def _realtime(recipe: dict[str, Any]) -> bool:
    return any(layer.get("delay", 0) > 0 for layer in recipe["layers"])


def _curve(rows: Sequence[dict[str, str]], phase: str) -> tuple[tuple[int, float], ...]:
    """Evaluation return against environment steps in `phase`."""
    return tuple((int(r["step"]), float(r["return_mean"])) for r in rows if r["phase"] == phase)


class _End(NamedTuple):
    """Where a layer's start weights were saved: the run directory (resolved), the last phase that trained the layer
    there (-1 where that run did not train it: it was saved as it came in), and every phase of training behind that
    stack as `results.json` holds them (that run's up to this one, those behind its own start weights first), None
    where some cannot be read."""

    source: Path
    phase: int
    behind: tuple[dict[str, Any], ...] | None


def _whole_run(rows: Sequence[dict[str, str]], start: tuple[int, frozenset[Path], list[_End | None]]) \
        -> dict[str, Any]:
    """A run's `Run` fields over the whole of its training, from the steps behind its start weights on (`start`,
    as `_start_weights` gives them)."""
    before, sources, ends = start
    end = _continues(ends)
    return {"total_curve": _total_curve(rows, before), "phase_starts": _phase_starts(rows, before),
            "trained_before": before, "started_from": sources,
            "continues": None if end is None else (end.source, end.phase)}


def _start_weights(recipe: dict[str, Any], seen: frozenset[Path] = frozenset()) \
        -> tuple[int, frozenset[Path], list[_End | None]]:
    """The environment steps of training behind the weights a run's layers started from (`weights`), the run
    directories they came from (resolved), and for each such layer the run and phase that last trained it (None
    where none is known): each from the run directory holding that checkpoint, up to the end of the last phase
    that trained the layer (that run's start, where it trained it in none), with that run's own start weights behind
    it; a file outside a run directory (or in a run since moved) adds nothing."""
    steps, sources, ends = 0, frozenset[Path](), list[_End | None]()
    for layer in recipe["layers"]:
        if not layer.get("weights"):
            continue
        ends.append(None)
        from layered.schema import SEED  # (the schema loads torch: only for runs started from weights)

        source = Path(layer["weights"].replace(SEED, str(recipe["train"]["seed"]))).parent.parent.resolve()
        if source in seen or not (source / "metrics.csv").is_file():
            continue
        try:
            rows = _metrics(source)
            learns = {r["phase"]: r["learn"].split("+") for r in rows}.values()  # each phase's, in order
            learned = [i for i, names in enumerate(learns) if layer["name"] in names]
            earlier, behind, before = _start_weights(tomllib.loads((source / "recipe.toml").read_text()),
                                                     seen | {source})
            sources |= {source, *behind}
            last = learned[-1] if learned else -1  # -1: a layer that run did not train, as it was at its start
            steps = max(steps, earlier + sum(_phase_ends(rows)[: last + 1]))
            ends[-1] = _End(source, last, _phases_until(source, last, before))
        except (OSError, ValueError, KeyError, TypeError, tomllib.TOMLDecodeError) as e:
            print(f"layered: warning: {source}, where layer {layer['name']!r} started from, cannot be read "
                  f"({e.__class__.__name__}: {e}); its steps are not counted", file=sys.stderr)
    return steps, sources, ends


def _continues(ends: Sequence[_End | None]) -> _End | None:
    """Where a run's stack continues from: where every layer it started from weights came from one run, that run's
    end of the latest phase that trained one of them (the stack of that phase's end: a layer that run did not train
    is in it as it came in); else None, also where that run trained none of them."""
    known = [end for end in ends if end is not None]
    if not known or len(known) < len(ends) or len({end.source for end in known}) > 1:
        return None
    latest = max(known, key=lambda end: end.phase)
    return latest if latest.phase >= 0 else None


def _phases_until(source: Path, phase: int, ends: Sequence[_End | None]) -> tuple[dict[str, Any], ...] | None:
    """The phases of training behind the stack of run `source` at the end of its phase `phase` (-1: at its start):
    its own up to that one (results.json, or the finished phases of a run still training), those behind the stack
    it continues (`ends`: its layers' start weights) first; None where some are not known."""
    earlier = (end.behind if (end := _continues(ends)) else None) if ends else ()
    if earlier is None or phase < 0:  # (a layer the run passed on untrained: only what came in is behind it)
        return earlier
    file = next((f for f in (source / "results.json", source / PHASES_FILE) if f.is_file()), None)
    if file is None:
        return None
    try:
        phases = tuple(p for p in json.loads(file.read_text())["phases"] if p["phase"] <= phase)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (*earlier, *phases) if len(phases) == phase + 1 else None


def _phase_ends(rows: Sequence[dict[str, str]]) -> list[int]:
    """The steps each phase ran, in order: its last evaluation's step."""
    phases = dict.fromkeys(r["phase"] for r in rows)
    return [max(int(r["step"]) for r in rows if r["phase"] == phase) for phase in phases]


def _total_curve(rows: Sequence[dict[str, str]], before: int = 0) -> tuple[tuple[int, float], ...]:
    """Evaluation return against environment steps since training began (`before`: the steps behind the run's
    start weights), phases laid end to end.

    A later phase's first evaluation falls on the step where the previous phase ended, beside that phase's last:
    both are kept, so that the curve shows the hand-over there (the weights `train.select` hands on, and the layer
    the phase adds, still acting at random)."""
    points: list[tuple[int, float]] = []
    offset = before
    for phase in dict.fromkeys(r["phase"] for r in rows):
        steps = [(int(r["step"]), float(r["return_mean"])) for r in rows if r["phase"] == phase]
        points += [(offset + s, v) for s, v in steps]
        offset += max(s for s, _ in steps)
    return tuple(points)


def _phase_starts(rows: Sequence[dict[str, str]], before: int = 0) -> tuple[int, ...]:
    """The steps since training began at which each phase after the first started."""
    return tuple(before + int(x) for x in np.cumsum(_phase_ends(rows))[:-1])


@dataclass(frozen=True)
class Setup:
    """The runs of one (environment, method) pair, one per seed; the method is the recipe's name."""

    env: str
    label: str
    runs: tuple[Run, ...]

    @property
    def method(self) -> str:
        return self.runs[0].method

    @property
    def realtime(self) -> bool:
        """Whether the setup's runs are of the real-time setting (a layer acts with a delay)."""
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


def group(runs: Iterable[Run]) -> list[Setup]:
    """Runs grouped by (environment, method), in the paper's method order; runs of different recipes under one
    label are told apart first (`told_apart`)."""
    by_key: dict[tuple[str, str], list[Run]] = {}
    for run in told_apart(runs):
        by_key.setdefault((run.env, run.method), []).append(run)
    setups = [Setup(env, rs[0].label, tuple(sorted(rs, key=lambda r: r.seed))) for (env, _), rs in by_key.items()]
    for s in setups:
        if twice := sorted(seed for seed, runs in Counter(r.seed for r in s.runs).items() if runs > 1):
            paths = ", ".join(str(r.path) for r in s.runs if r.seed == twice[0])
            several = len(twice) > 1
            print(f"layered: warning: {s.env} {s.method}: seed{'s' * several} {', '.join(map(str, twice))} "
                  f"come{'s' * (not several)} from more than one run of the same setup (seed {twice[0]}: {paths}), "
                  "each counted as a seed of its own", file=sys.stderr)

    def order(s: Setup) -> tuple[str, int, str]:
        rank = METHOD_ORDER.index(s.method) if s.method in METHOD_ORDER else len(METHOD_ORDER)
        return (s.env, rank, s.label)

    return sorted(setups, key=order)


def told_apart(runs: Iterable[Run]) -> list[Run]:
    """The runs, each label lengthened by the recipe's `key=value` wherever runs of its environment and label differ
    at that key (a recipe trained with overrides keeps its name), so that their seeds are not pooled. A key whose
    default is unset (`unset_by_default`) is `unset` where a recipe lacks it, as a resolved recipe leaves it out;
    any other key that some of them lack does not count: a run of older code lacks keys added since."""
    by_key: dict[tuple[str, str], list[Run]] = {}
    for run in runs:
        by_key.setdefault((run.env, run.label), []).append(run)
    out = []
    for rs in by_key.values():
        settings = [dict(r.setting) for r in rs]
        keys = set().union(*settings)
        counted = {k for k in keys if all(k in s for s in settings)}
        if counted != keys:
            from layered.schema import unset_by_default  # (the schema loads torch: only where keys are missing)

            unset = unset_by_default()
            counted |= {k for k in keys if re.sub(LAYER_KEY, "layers.*.", k) in unset}
        differ = sorted(k for k in counted if len({s.get(k, UNSET) for s in settings}) > 1)
        named = _naming(settings, differ)
        out += [replace(r, label=" ".join([r.label, *(f"{k}={s.get(k, UNSET)}" for k in named)]),
                        unnamed=tuple(f"{k}={s.get(k, UNSET)}" for k in differ if k not in named)) if differ else r
                for r, s in zip(rs, settings, strict=True)]
    return out


def _naming(settings: Sequence[dict[str, str]], differ: Sequence[str]) -> list[str]:
    """The differing keys that name the setups: all but those of long values (paths, phase lists) that the others
    already tell apart, the longest left out first."""
    def setups(keys: Sequence[str]) -> int:
        return len({tuple(s.get(k, UNSET) for k in keys) for s in settings})

    def longest(key: str) -> int:
        return max(len(s.get(key, UNSET)) for s in settings)

    named = list(differ)
    for key in sorted((k for k in differ if longest(k) > LONG_VALUE), key=longest, reverse=True):
        rest = [k for k in named if k != key]
        if rest and setups(rest) == setups(differ):
            named = rest
    return named


LONG_VALUE = 24
"""Characters beyond which a differing value is left out of setup labels where other keys tell the setups apart
(report's Runs table lists it)."""


UNSET = "unset"
"""How a setup's label names a key left unset."""
LAYER_KEY = r"^layers\.[^.]+\."
"""A layer's key as `_setting` writes it, `layers.<name>.`."""


def find_runs(paths: Sequence[Path], unfinished: bool = False) -> list[Run]:
    """Every finished run in `paths`, each a run directory or a folder holding run directories; with
    `unfinished`, every run still training or stopped before its end too, at its last evaluation."""
    found: list[Run] = []
    for path in paths:
        dirs = _run_dirs(path, "results.json")
        left = _unfinished_dirs(path)
        if not dirs and not (unfinished and left):
            hint = f"; {count(len(left), 'run')} in it not finished: --unfinished reports them" if left else ""
            raise FileNotFoundError(f"{path}: no finished runs (no results.json) in it{hint}")
        if left and not unfinished:
            print(f"layered: note: {count(len(left), 'run')} in {path} not finished, left out (--unfinished reports "
                  "such runs at their last evaluation)", file=sys.stderr)
        loads = [(d, load_finished_run) for d in dirs] + [(d, load_unfinished_run) for d in left if unfinished]
        for d, load in sorted(loads, key=lambda item: item[0]):
            try:
                found.append(load(d))
            except BrokenRun as e:
                print(f"layered: warning: {e}; reporting the other runs", file=sys.stderr)
    if not found:
        raise FileNotFoundError(f"no readable {'' if unfinished else 'finished '}run in {', '.join(map(str, paths))}")
    return found


def _unfinished_dirs(path: Path) -> list[Path]:
    """The run directories at or under `path` that log evaluations but hold no results yet."""
    return [d for d in _run_dirs(path, "metrics.csv")
            if not (d / "results.json").exists() and (d / "recipe.toml").exists()]


def _run_dirs(path: Path, name: str) -> list[Path]:
    """`path` if it holds the file `name`, else every folder under it that does."""
    if (path / name).exists():
        return [path]
    return sorted(p.parent for p in path.rglob(name))
