"""Results as people read them: a Markdown table and learning-curve plots."""

from __future__ import annotations

import csv
import os
import re
import shutil
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from layered.compare import (ACROSS_COLUMNS, COLUMNS, RESAMPLES, across_csv_row, across_envs, across_table, adjusted,
                             between_phases, between_setups, comparisons_table, csv_row, number, phased)
from layered.progress import count

if TYPE_CHECKING:
    from layered.summary import Run, Setup

DEFAULT_SWEEP = [round(0.1 * k, 1) for k in range(11)]  # the thresholds of the paper's Fig. 2
SWEEP_FILE = "threshold-sweep.csv"
"""A run's threshold sweep on `DEFAULT_SWEEP` and its `eval.episodes`, in its eval/ folder: the one Fig. 2 is drawn
from."""


def kept_thresholds(path: Path) -> list[float]:
    """The thresholds of the sweep kept in `path`, in its order."""
    with path.open(newline="") as f:
        return [float(row["threshold"]) for row in csv.DictReader(f)]


def kept_episodes(path: Path) -> int | None:
    """The episodes per threshold of the sweep kept in `path`; None for one kept before they were recorded."""
    with path.open(newline="") as f:
        counts = {row.get("episodes") or "" for row in csv.DictReader(f)}
    return int(counts.pop()) if len(counts) == 1 and "" not in counts else None


def figure_sweep(path: Path, episodes: int | None) -> bool:
    """Whether the sweep kept in `path` is the one Fig. 2 is drawn from: the default grid, on `episodes` episodes (the
    run's `eval.episodes`) each."""
    return path.exists() and kept_thresholds(path) == DEFAULT_SWEEP and kept_episodes(path) == episodes


LEGEND_WIDTH = 44
"""Characters per line of a setup's name in a figure's legend, which wraps longer names (settings, paths) so that
the legend stays within its plot."""
TITLE_WIDTH = 64  # characters of a figure's title per line: a setup named by its overrides can be long


def _activity(row: dict[str, Any], prefix: str, fmt: str = "{:.0%}") -> str:
    return ", ".join(f"{k[len(prefix):]} {fmt.format(v)}" for k, v in row.items() if k.startswith(prefix))


def _macs(value: float) -> str:
    return f"{value / 1e6:.2f} M MACs"


def _percent(row: dict[str, Any], key: str) -> str:
    """A share of `row` as a percentage; n/a where the row has none (written before it was measured)."""
    value = number(row.get(key))
    return "n/a" if value != value else f"{100 * value:.1f}%"


def results_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of per-phase (or per-evaluation) results rows as written to results.json; for
    phases, a second table of the final and best weights evaluated again on fresh episodes."""
    columns = ["phase", "learns", "present", "return", "AUC", "action repetition", "of it at the action bounds",
               "of it held by the rules", "jerk", "decisions / episode", "compute / episode", "evaluated", "acted",
               "mean \\|contribution\\|"]
    lines = ["| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    for r in rows:
        auc = "n/a" if r.get("auc") is None else f"{r['auc']:.3f}"
        lines.append(
            f"| {r.get('phase', '')} | {'+'.join(r.get('learn', []))} | {'+'.join(r.get('active', []))} "
            f"| {r['return_mean']:.1f} ± {r['return_std']:.1f} | {auc} | {100 * r['repetition']:.1f}% "
            f"| {_percent(r, 'repetition_at_bounds')} | {_percent(r, 'repetition_held')} | {r['jerk']:.3f} "
            f"| {r['decisions']:.1f} of {r['episode_steps']:.{0 if float(r['episode_steps']).is_integer() else 1}f} "
            f"| {_macs(r['compute'])} "
            f"| {_activity(r, 'decided_')} | {_activity(r, 'acted_')} | {_activity(r, 'contribution_', '{:.3f}')} |"
        )
    fresh = [r for r in rows if "fresh_final_return_mean" in r]
    if fresh:
        lines += ["", "Final and best weights of each phase, each evaluated again on fresh episodes (the best "
                  "evaluation's own return is biased upwards by the choice):", "",
                  "| phase | final: return | final: action repetition | final: at the action bounds | final: held "
                  "by the rules | best: step | best: return at that evaluation | best: return | best: action "
                  "repetition | best: at the action bounds | best: held by the rules |", "|---" * 11 + "|"]
        lines += [
            f"| {r['phase']} | {r['fresh_final_return_mean']:.1f} ± {r['fresh_final_return_std']:.1f} "
            f"| {100 * r['fresh_final_repetition']:.1f}% | {_percent(r, 'fresh_final_repetition_at_bounds')} "
            f"| {_percent(r, 'fresh_final_repetition_held')} | {r['best_step']} | {r['best_return_mean']:.1f} "
            f"| {r['fresh_best_return_mean']:.1f} ± {r['fresh_best_return_std']:.1f} "
            f"| {100 * r['fresh_best_repetition']:.1f}% | {_percent(r, 'fresh_best_repetition_at_bounds')} "
            f"| {_percent(r, 'fresh_best_repetition_held')} |"
            for r in fresh
        ]
    return "\n".join(lines)


def pyplot() -> Any:
    """matplotlib's pyplot, drawing off-screen; imported only when a figure is drawn (it is large)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _steps_axis(ax: Any, label: str) -> None:
    """Label an axis of environment steps, every tick in the unit of the axis's end (0.5k ... 2k; 250k ... 1M) so
    that long runs stay legible."""
    from matplotlib.ticker import FuncFormatter

    def steps(x: float, _: int) -> str:
        end = max(abs(v) for v in ax.get_xlim())
        scale, unit = (1e6, "M") if end >= 1e6 else (1e3, "k") if end >= 1e3 else (1.0, "")
        return f"{x / scale:g}{unit}" if x else "0"

    ax.set_xlabel(label)
    ax.xaxis.set_major_formatter(FuncFormatter(steps))


def band(mean: Any, std: Any, lowest: Any = None, highest: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """mean ± std, clipped to the lowest and highest of the values it summarises where known: a band
    never claims returns beyond those seen (such as above a task's maximum)."""
    mean = np.asarray(mean, np.float64)
    low, high = mean - std, mean + std
    if lowest is not None:
        low = np.maximum(low, np.asarray(lowest, np.float64))
    if highest is not None:
        high = np.minimum(high, np.asarray(highest, np.float64))
    return low, high


def plot_curves(metrics_csv: Path, out_png: Path, title: str) -> None:
    """Evaluation return against base steps, one line per phase, with ±1 std over episodes (clipped to
    the lowest and highest episode return)."""
    plt = pyplot()
    with metrics_csv.open() as f:
        rows = list(csv.DictReader(f))
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for phase in dict.fromkeys(r["phase"] for r in rows):
        sel = [r for r in rows if r["phase"] == phase]
        x = [int(r["step"]) for r in sel]
        y = [float(r["return_mean"]) for r in sel]
        s = [float(r["return_std"]) for r in sel]
        line, = ax.plot(x, y, marker="o", ms=3, label=f"phase {phase}: {sel[0]['learn']} learns")
        ax.fill_between(x, *band(y, np.asarray(s), *_extremes(sel)), color=line.get_color(), alpha=0.2)
    _steps_axis(ax, "environment steps in phase")
    ax.set_ylabel("evaluation return")
    ax.set_title(textwrap.fill(title, TITLE_WIDTH))
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.18), frameon=False,
              ncols=min(3, len(ax.get_lines())))  # (below the axes, off the bands)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def _extremes(rows: Sequence[dict[str, Any]]) -> tuple[list[float] | None, list[float] | None]:
    """The lowest and highest episode return of each evaluation row, where the rows record them."""
    if not rows or not rows[0].get("return_min"):
        return None, None
    return [float(r["return_min"]) for r in rows], [float(r["return_max"]) for r in rows]


def plot_episode(trace: Sequence[Any], layers: Sequence[str], out_png: Path, title: str,
                 bounds: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """One episode: above, when each layer decided (ticks) and changed the action, contributing a non-zero part of
    it (squares); below, the executed action per dimension, on the action's `bounds` where given."""
    plt = pyplot()
    steps = range(len(trace))
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(9, 2 + 0.4 * len(layers)), sharex=True, constrained_layout=True,
        gridspec_kw={"height_ratios": [max(1, len(layers)), 3]},
    )
    for row, name in enumerate(layers):
        decided = [t for t in steps if name in trace[t].decided]
        acted = [t for t in steps if name in trace[t].acted]
        top.scatter(decided, [row] * len(decided), marker="|", s=60, color="0.6", label="decided" if row == 0 else None)
        top.scatter(acted, [row + 0.25] * len(acted), marker="s", s=6, color=f"C{row}")
    top.scatter([], [], marker="s", s=6, color="0.2", label="changed the action")  # (the key, in no layer's colour)
    top.set_yticks(range(len(layers)), layers)
    top.set_ylim(-0.6, len(layers) - 0.2)
    top.invert_yaxis()
    top.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small", frameon=False)  # (clear of the title)
    top.set_title(textwrap.fill(title, 2 * TITLE_WIDTH), loc="left")
    actions = [record.action for record in trace]
    for d in range(len(actions[0]) if actions else 0):
        bottom.step(list(steps), [a[d] for a in actions], where="post", lw=1, label=f"action[{d}]")
    bottom.set_xlabel("base step")
    bottom.set_ylabel("executed action")
    if bounds is not None:
        low, high = float(np.min(bounds[0])), float(np.max(bounds[1]))
        bottom.set_ylim(low - 0.05 * (high - low), high + 0.05 * (high - low))
    bottom.grid(alpha=0.3)
    if actions and len(actions[0]) <= 8:
        bottom.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small", frameon=False)  # (off the lines)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


Metric = tuple[str, str, str]  # (results key, column name, format of mean and std)

TABLE_1: list[Metric] = [("auc", "AUC", "{:.3f}"), ("return_mean", "return", "{:.1f}")]
TABLE_2: list[Metric] = [("repetition", "action repetition", "{:.1%}"),
                         ("repetition_at_bounds", "of it at the action bounds", "{:.1%}"),
                         ("repetition_held", "of it held by the rules", "{:.1%}"),
                         ("decisions", "decisions", "{:.1f}")]
EXTRA_MEASURES: list[Metric] = [("jerk", "jerk", "{:.3f}"), ("compute", "MACs / episode", "{:.3g}")]
TABLE_3: list[Metric] = [
    ("auc", "AUC", "{:.3f}"), ("return_mean", "return", "{:.1f}"), ("repetition", "AR", "{:.1%}"),
    ("repetition_at_bounds", "AR at bounds", "{:.1%}"), ("repetition_held", "AR held", "{:.1%}"),
]
PER_SEED: list[Metric] = [
    ("return_mean", "return", "{:.1f}"), ("auc", "AUC", "{:.3f}"), ("run_auc", "AUC, whole run", "{:.3f}"),
    ("fresh_final_return_mean", "final", "{:.1f}"), ("fresh_best_return_mean", "best", "{:.1f}"),
    ("best_step", "best step", "{:.0f}"), ("fresh_best_repetition", "best AR", "{:.1%}"),
    ("fresh_best_repetition_at_bounds", "best AR at bounds", "{:.1%}"),
    ("fresh_best_repetition_held", "best AR held", "{:.1%}"),
]
"""The per-seed table's measures of a run's last phase (the whole run's AUC only where it trained in phases, or
continued a stack that another run's phases trained: `compare.phased`)."""
FINAL_AND_BEST: list[Metric] = [
    ("fresh_final_return_mean", "final", "{:.1f}"), ("best_return_mean", "best as selected", "{:.1f}"),
    ("fresh_best_return_mean", "best", "{:.1f}"), ("fresh_final_repetition", "final AR", "{:.1%}"),
    ("fresh_best_repetition", "best AR", "{:.1%}"),
    ("fresh_final_repetition_at_bounds", "final AR at bounds", "{:.1%}"),
    ("fresh_best_repetition_at_bounds", "best AR at bounds", "{:.1%}"),
    ("fresh_final_repetition_held", "final AR held", "{:.1%}"),
    ("fresh_best_repetition_held", "best AR held", "{:.1%}"),
]


def _spread(mean: float, std: float, seeds: int, fmt: str) -> str:
    """mean ± std over `seeds` seeds as a cell; n/a where there is no value."""
    if mean != mean:  # NaN: no value for this setup
        return "n/a"
    if seeds == 1:  # no spread over seeds to show
        return f"{fmt.format(mean)} (1 seed)"
    return f"{fmt.format(mean)} ± {fmt.format(std)}"


def _cell(setup: Setup, key: str, fmt: str) -> str:
    mean, std = setup.stat(key)
    return _spread(mean, std, len(setup.runs), fmt)


def wide_table(setups: Sequence[Setup], metrics: Sequence[Metric]) -> str:
    """One row per environment, one column per (metric, method): mean ± std over seeds."""
    methods = list(dict.fromkeys(s.method for s in setups))
    envs = list(dict.fromkeys(s.env for s in setups))
    head = ["environment"] + [f"{name}: {m}" for _, name, _ in metrics for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for env in envs:
        here = {s.method: s for s in setups if s.env == env}
        cells = [_cell(here[m], key, fmt) if m in here else "" for key, _, fmt in metrics for m in methods]
        lines.append("| " + " | ".join([env, *cells]) + " |")
    return "\n".join(lines)


def from_report(out: Path, path: Path) -> str:
    """`path` as the report in `out` names it: relative to the report's directory, so that it can be followed from
    report.md wherever the report was made from."""
    return os.path.relpath(path.resolve(), out.resolve())


def seeds_table(setups: Sequence[Setup], out: Path) -> str:
    """Which runs make up each setup (their directories relative to the report's, `out`): the traceability of every
    number in the tables."""
    lines = ["| environment | setup | seed ids | run directories |", "|---|---|---|---|"]
    for s in setups:
        dirs = ", ".join(from_report(out, r.path) + ("" if r.finished else f" ({r.stands})") for r in s.runs)
        setup = s.label + (f" ({', '.join(s.runs[0].unnamed)})" if s.runs[0].unnamed else "") + \
            ("" if s.runs[0].finished else " (unfinished)")
        lines.append(f"| {s.env} | {setup} | {', '.join(str(r.seed) for r in s.runs)} | {dirs} |")
    return "\n".join(lines)


def per_seed_table(setup: Setup) -> str:
    """One row per seed of a setup: its last phase's measures and, where the stack trained in phases, each
    earlier phase's best weights on fresh episodes (for TLA, the slow layer alone), so that what the means
    hide shows: a seed that stands still, a phase that lowers the layer it started from."""
    earlier = [(i, p) for i, p in enumerate(setup.runs[0].phases[:-1]) if "fresh_best_return_mean" in p]
    measures = [m for m in PER_SEED if m[0] != "run_auc" or phased(setup.runs)]
    columns = [(f"phase {p['phase']} ({'+'.join(p.get('learn', []))}): best", "{:.1f}") for _, p in earlier]
    columns += [(name, fmt) for _, name, fmt in measures]
    table = np.array([[number(r.phases[i].get("fresh_best_return_mean")) if i < len(r.phases) - 1 else np.nan
                       for i, _ in earlier] + [number(r.final.get(key)) for key, _, _ in measures]
                      for r in setup.runs])
    lines = ["| " + " | ".join(["seed", *(name for name, _ in columns)]) + " |", "|---" * (len(columns) + 1) + "|"]
    for r, values in zip(setup.runs, table, strict=True):
        cells = ["n/a" if v != v else fmt.format(v) for v, (_, fmt) in zip(values, columns, strict=True)]
        lines.append("| " + " | ".join([str(r.seed), *cells]) + " |")
    spread = [_spread(float(np.mean(c)), float(np.std(c)), len(c), fmt)
              for c, (_, fmt) in zip(table.T, columns, strict=True)]
    lines.append("| " + " | ".join(["mean ± std", *spread]) + " |")
    return "\n".join(lines)


def write_seeds_csv(setups: Sequence[Setup], path: Path) -> None:
    """Every phase of every run on a row of its own (setup, seed, phase, what it learned and every measure of
    `results.json`, and the run's directory relative to the report's), for analyses of one's own."""
    rows: list[tuple[Setup, Run, dict[str, Any]]] = [(s, r, p) for s in setups for r in s.runs
                                                     for p in (r.phases or (r.final,))]
    keys = sorted({k for _, _, p in rows for k, v in p.items() if k != "phase" and not np.isnan(number(v))})
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env", "label", "method", "seed", "phase", "learn", *keys, "run"])
        for s, r, p in rows:
            writer.writerow([s.env, s.label, s.method, r.seed, p.get("phase", ""), "+".join(p.get("learn", [])),
                             *(p.get(k, "") for k in keys), from_report(path.parent, r.path)])


CURVE_FRACTIONS = (0.1, 0.25, 0.5, 0.75, 1.0)
"""Where along a setup's last-phase curve the report's table of it reads the return: a tenth of it ... its end."""


def curve_points(setup: Setup, fractions: Sequence[float] = CURVE_FRACTIONS) -> list[tuple[float, float, float]]:
    """(step, mean, std over seeds) of a setup's evaluation return at the evaluations of its last-phase curve
    nearest to each of `fractions` of that curve's last step."""
    steps, mean, std, _, _ = setup.curve()
    picks = [int(np.argmin(np.abs(steps - fraction * steps[-1]))) for fraction in fractions]
    return [(float(steps[i]), float(mean[i]), float(std[i])) for i in picks]


def _steps(n: float) -> str:
    """A number of environment steps as the curves' axes write it: 25k, 1.5M."""
    for unit, size in (("M", 1e6), ("k", 1e3)):
        if n >= size:
            return f"{n / size:.3g}{unit}"
    return f"{n:.0f}"


def curve_table(setups: Sequence[Setup]) -> str:
    """The learning curves in numbers: each setup's evaluation return, mean ± std over seeds, along its last phase
    (`CURVE_FRACTIONS`, each cell with the step it was read at)."""
    head = ["environment", "setup", *(f"{fraction:.0%}" for fraction in CURVE_FRACTIONS)]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for s in setups:
        cells = [f"{_spread(mean, std, len(s.runs), '{:.1f}')} at {_steps(step)}"
                 for step, mean, std in curve_points(s)]
        lines.append("| " + " | ".join([s.env, s.method, *cells]) + " |")
    return "\n".join(lines)


def write_curves_csv(setups: Sequence[Setup], path: Path) -> None:
    """Every point of every setup's learning curves, as the figure draws them: over the last phase and over the
    whole run, evaluation by evaluation, mean, std, lowest and highest over seeds."""
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env", "label", "method", "seeds", "curve", "step", "return_mean", "return_std",
                         "return_lowest", "return_highest"])
        for s in setups:
            for whole_run, view in ((False, "last phase"), (True, "whole run")):
                for point in zip(*s.curve(whole_run), strict=True):
                    writer.writerow([s.env, s.label, s.method, len(s.runs), view, *(float(v) for v in point)])


def plot_setup_curves(setups: Sequence[Setup], out_png: Path) -> None:
    """Learning curves per environment, mean over seeds with a ±1 std band (clipped to the lowest and
    highest seed): over the last phase
    (what the AUC measures) and, where a setup trains in several phases, over the whole run, so
    that setups can be compared at the same number of environment steps."""
    plt = pyplot()
    envs = list(dict.fromkeys(s.env for s in setups))
    phased = {env: any(len(r.total_curve) > len(r.curve) or r.trained_before
                       for s in setups if s.env == env for r in s.runs) for env in envs}
    views = [(False, "environment steps (last phase)"), (True, "environment steps (whole run)")]
    views = views[: 1 + any(phased.values())]
    fig, axes = plt.subplots(len(views), len(envs), figsize=(5.5 * len(envs), 4 * len(views)), squeeze=False,
                             constrained_layout=True)
    for row, (whole_run, xlabel) in zip(axes, views, strict=True):
        for ax, env in zip(row, envs, strict=True):
            if whole_run and not phased[env]:
                ax.axis("off")
                ax.text(0.5, 0.5, f"{env}:\nevery setup trains in one phase,\nso its whole run is the curve above",
                        ha="center", va="center", transform=ax.transAxes, fontsize="small")
                continue
            starts: dict[tuple[int, int], list[str]] = {}  # (phase, step) -> the setups whose phase starts there
            for s in (s for s in setups if s.env == env):
                steps, mean, std, lowest, highest = s.curve(whole_run)
                label = textwrap.fill(f"{s.method} ({count(len(s.runs), 'seed')})", LEGEND_WIDTH)
                line, = ax.plot(steps, mean, label=label)
                ax.fill_between(steps, *band(mean, std, lowest, highest), color=line.get_color(), alpha=0.2)
                for phase, start in enumerate(s.runs[0].phase_starts if whole_run else (), start=1):
                    starts.setdefault((phase, start), []).append(s.method)
            for (phase, start), methods in starts.items():  # one marker per start, naming every setup it is of
                ax.axvline(start, color="0.4", ls=":", lw=1)
                ax.annotate(textwrap.fill(f"phase {phase}: {', '.join(methods)}", 24), (start, 1),
                            xycoords=("data", "axes fraction"), xytext=(2, -2), textcoords="offset points", va="top",
                            fontsize="x-small", color="0.3")
            ax.set_title(f"{env}: {'whole run' if whole_run else 'last phase'}")
            _steps_axis(ax, xlabel)
            ax.set_ylabel("evaluation return")
            ax.grid(alpha=0.3)
            ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)  # (off the data)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def _slug(setup: Setup) -> str:
    return re.sub(r"[^\w.-]+", "-", f"{setup.env}-{setup.method}").strip("-")


def _eval_episodes(run: Run) -> int | None:
    """The episodes of a run's evaluations (its resolved recipe's `eval.episodes`; None where it does not say)."""
    episodes = dict(run.setting).get("eval.episodes")
    return None if episodes is None else int(episodes)


def _threshold_and_gallery_figures(setups: Sequence[Setup], out: Path) -> list[str]:
    """Fig. 2 per setup from its runs' `layered eval --threshold-sweep` (mean over seeds), and the
    first gallery of states where a layer acts (`layered eval --gallery`)."""
    parts: list[str] = []
    for s in setups:
        sweeps = [p for r in s.runs if figure_sweep(p := r.path / "eval" / SWEEP_FILE, _eval_episodes(r))]
        if sweeps:
            per_run = []
            for path in sweeps:
                with path.open() as f:
                    per_run.append({float(row["threshold"]): row for row in csv.DictReader(f)})
            common = sorted(set.intersection(*(set(p) for p in per_run)))
            rows = [{
                "threshold": t,
                "return_mean": np.mean([float(p[t]["return_mean"]) for p in per_run]),
                "return_min": min(float(p[t].get("return_min") or p[t]["return_mean"]) for p in per_run),
                "return_max": max(float(p[t].get("return_max") or p[t]["return_mean"]) for p in per_run),
                "return_std": np.std([float(p[t]["return_mean"]) for p in per_run]) if len(per_run) > 1
                else float(per_run[0][t]["return_std"]),
                "repetition": np.mean([float(p[t]["repetition"]) for p in per_run]),
            } for t in common]
            name = f"threshold-{_slug(s)}.png"
            each = "" if (episodes := _eval_episodes(s.runs[0])) is None else f", {count(episodes, 'episode')} each"
            plot_threshold_sweep(rows, out / name,
                                 f"{s.env} {s.method}: threshold ({count(len(sweeps), 'seed')}{each})")
            with (out / name).with_suffix(".csv").open("w", newline="") as f:  # (the figure's points)
                writer = csv.DictWriter(f, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)
            parts += [f"### Return and action frequency against the threshold: {s.env}, {s.method}", "",
                      f"![threshold sweep]({name})", ""]
        galleries = sorted(p for r in s.runs for p in (r.path / "eval").glob("gallery-*.png"))
        if galleries:
            name = f"gallery-{_slug(s)}.png"
            shutil.copyfile(galleries[0], out / name)
            parts += [f"### States where a layer acts: {s.env}, {s.method} ({from_report(out, galleries[0])})", "",
                      f"![gallery]({name})", ""]
    return parts


def write_report(setups: Sequence[Setup], out: Path) -> str:
    """Tables 1-3 as Markdown (report.md) and CSV (summary.csv), the setups and phases compared over seeds
    (comparisons.csv) and the methods over environments (across-envs.csv), and learning curves (curves.png, and
    their points in curves.csv)."""
    out.mkdir(parents=True, exist_ok=True)
    turn = [s for s in setups if not s.realtime]
    realtime = [s for s in setups if s.realtime]
    parts = ["# Results", "",
             "Mean ± standard deviation over seeds of each run's final evaluation (last phase); "
             "AUC is the normalised area under the last phase's evaluation curve.", ""]
    if any(not r.finished for s in setups for r in s.runs):
        parts += ["Setups marked *(unfinished)* are runs still training or stopped before their end, each taken at "
                  "its last evaluation (where that was is in [Runs](#runs)), their best step at their best evaluation "
                  "so far: their AUC and fresh-episode columns are n/a until they finish.", ""]
    if turn:
        parts += ["## Table 1: normalised AUC and average return", "", wide_table(turn, TABLE_1), "",
                  "## Table 2: action repetition and decisions per episode", "", wide_table(turn, TABLE_2), "",
                  "## Smoothness and compute: jerk (mean |a_t - a_t-1|) and multiply-accumulates per episode", "",
                  wide_table(turn, EXTRA_MEASURES), ""]
    if realtime:
        parts += ["## Table 3: real-time setting", "", wide_table(realtime, TABLE_3), ""]
    if any("fresh_final_return_mean" in r.final for s in setups for r in s.runs):
        parts += ["## Final and best weights, each evaluated again on fresh episodes", "",
                  "Return and action repetition (AR) of each run's last phase: its final weights, and the "
                  "weights of its best evaluation (the paper's protocol), both on `eval.fresh_episodes` episodes "
                  "of a seed never used for choosing; \"best as selected\" is that best evaluation's own return, "
                  "biased upwards by the choice.", "", wide_table(setups, FINAL_AND_BEST), ""]
    compared = adjusted(between_setups(setups) + between_phases(setups))
    if compared:
        parts += ["## Comparisons over seeds", "",
                  "Each finished setup against each one listed before it for the same environment and setting "
                  "(real-time or not), as independent samples of seeds (Welch's t-test) or, where each seed's two runs "
                  "share trained layers (one started from the other's weights, or both from one run's), seed by seed "
                  "(a paired t-test), and each phase of a stack trained in phases against the phase before it, seed by "
                  "seed (a setup whose runs continued another's stacks: its first phase against the phase it "
                  "continued): the difference of the means with its 95% confidence interval, the two-sided p-value, "
                  "and how often the first is above the second (over all pairs of a seed of each, or over the seeds; "
                  "ties count half). \"AUC\" is the last phase's, as in the paper; \"AUC, whole run\", where one of "
                  "the two trained in phases, counts every step behind each run's stack (each phase's AUC weighted by "
                  "its steps, those of the run whose stack it continued first). \"p, Holm\" is the p-value adjusted "
                  "for every comparison of this report (Holm's method): where it is below 0.05, the chance that any of "
                  "them is below by chance alone is at most 5%. With few seeds these tests have little power: a "
                  "p-value above 0.05 says that the seeds do not tell the two apart, not that the two are the same. "
                  "The rows are in `comparisons.csv`.", "",
                  comparisons_table(compared), ""]
    across = across_envs(setups)
    if across:
        parts += ["## Across environments", "",
                  "Each method against each one listed before it, over every environment (of one setting) where "
                  "both finished: the probability that a seed of the first comes out above a seed of the second (ties "
                  "half), averaged over the environments (Agarwal et al., 2021), which needs no common scale of "
                  "returns; 0.5 where the two are alike. The 95% interval is from a stratified bootstrap: each "
                  f"environment's seeds of each method resampled {RESAMPLES} times. The rows are in `across-envs.csv`.",
                  "", across_table(across), ""]
    parts += ["## Per seed", "",
              "Each seed's last phase: its final evaluation's return, AUC, and its final and best weights on fresh "
              "episodes (with the best evaluation's step and the best weights' action repetition, AR); for a stack "
              "trained in phases, each earlier phase's best weights on fresh episodes too. Every phase of every run "
              "is a row of `seeds.csv`.", ""]
    for s in setups:
        parts += [f"### {s.env}, {s.label}", "", per_seed_table(s), ""]
    parts += ["## Learning curves", "", "![learning curves](curves.png)", "",
              "In numbers: each setup's evaluation return (mean ± std over seeds) along its last phase, at the "
              "evaluations nearest a tenth, a quarter, half and three quarters of its curve (so far, for an "
              "unfinished one) and at its end. Every point of both figures is a row of `curves.csv`.", "",
              curve_table(setups), ""]
    parts += _threshold_and_gallery_figures(setups, out)
    parts += ["## Runs", "", seeds_table(setups, out), ""]
    text = "\n".join(parts)
    (out / "report.md").write_text(text)
    keys = sorted({k for s in setups for r in s.runs for k in r.final if k != "phase"})
    with (out / "summary.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env", "label", "method", "seeds", *(f"{k}_{stat}" for k in keys for stat in ("mean", "std"))])
        for s in setups:
            stats = [v for k in keys for v in s.stat(k)]
            writer.writerow([s.env, s.label, s.method, " ".join(str(r.seed) for r in s.runs), *stats])
    write_seeds_csv(setups, out / "seeds.csv")
    write_curves_csv(setups, out / "curves.csv")
    with (out / "comparisons.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        writer.writerows(csv_row(r) for r in compared)
    with (out / "across-envs.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(ACROSS_COLUMNS)
        writer.writerows(across_csv_row(r) for r in across)
    plot_setup_curves(setups, out / "curves.png")
    return text


def plot_threshold_sweep(rows: Sequence[dict[str, Any]], out_png: Path, title: str) -> None:
    """Return (± std, clipped to the lowest and highest return) and action frequency (share of steps
    with a new action) against the threshold."""
    plt = pyplot()
    x = [float(r["threshold"]) for r in rows]
    mean = np.array([float(r["return_mean"]) for r in rows])
    low, high = band(mean, np.array([float(r["return_std"]) for r in rows]), *_extremes(rows))
    fig, ax = plt.subplots(figsize=(6.5, 4), constrained_layout=True)
    ax.errorbar(x, mean, yerr=[mean - low, high - mean], marker="o", color="C0", capsize=3)
    ax.set_xlabel("evaluation threshold (fraction of max action)")
    ax.set_ylabel("evaluation return", color="C0")
    other = ax.twinx()
    other.plot(x, [1 - float(r["repetition"]) for r in rows], marker="s", color="C1")
    other.set_ylabel("action frequency (new actions per step)", color="C1")
    other.set_ylim(0, 1.05)
    ax.set_title(textwrap.fill(title, TITLE_WIDTH), loc="left")
    ax.grid(alpha=0.3)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def _signed(values: Any) -> str:
    return " ".join(f"{float(v):+.2f}" for v in values[:3]) + (" ..." if len(values) > 3 else "")


def _content(frames: np.ndarray, margin: int = 10) -> tuple[slice, slice]:
    """The rows and columns where any of the frames differs from its top-left pixel's colour: the
    scene without the empty background that some renderers draw around it."""
    busy = np.any(frames != frames[:, :1, :1], axis=(0, 3))
    if not busy.any():
        return slice(None), slice(None)
    ys, xs = np.flatnonzero(busy.any(axis=1)), np.flatnonzero(busy.any(axis=0))
    return (slice(max(ys[0] - margin, 0), ys[-1] + margin + 1), slice(max(xs[0] - margin, 0), xs[-1] + margin + 1))


def save_gallery(shots: Sequence[tuple[int, int, Any, Any]], layer: str, out_png: Path, title: str) -> None:
    """The rendered states, four to a row (legible where a page shrinks the figure), each titled with its episode and
    step, the layer's part of the action and the executed action."""
    plt = pyplot()
    across = min(4, max(1, len(shots)))
    down = -(-max(1, len(shots)) // across)
    fig, axes = plt.subplots(down, across, figsize=(2.8 * across, 3.3 * down + 0.4), squeeze=False,
                             layout="constrained")  # keeps the title clear of the frames' own titles
    for ax in axes.flat:
        ax.axis("off")
    rows, cols = _content(np.asarray([frame for _, _, frame, _ in shots])) if shots else (slice(None), slice(None))
    for ax, (episode, step, frame, record) in zip(axes.flat, shots, strict=False):
        ax.imshow(frame[rows, cols])
        ax.set_title(f"episode {episode}, step {step}\n{layer}: {_signed(record.contributions[layer])}\n"
                     f"action: {_signed(record.action)}", fontsize="small")
    fig.suptitle(textwrap.fill(title if shots else f"{title}: the layer never acted", 30 * across), fontsize="medium")
    fig.savefig(out_png, dpi=100, bbox_inches="tight")
    plt.close(fig)
