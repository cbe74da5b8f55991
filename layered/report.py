"""Results as people read them: a Markdown table and learning-curve plots."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def _activity(row: dict[str, Any], prefix: str) -> str:
    return ", ".join(f"{k[len(prefix):]} {100 * v:.0f}%" for k, v in row.items() if k.startswith(prefix))


def results_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of per-phase (or per-evaluation) results rows as written to results.json."""
    head = "| phase | learns | present | return | AUC | action repetition | decisions / episode | evaluated | acted |"
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for r in rows:
        auc = "n/a" if r.get("auc") is None else f"{r['auc']:.3f}"
        lines.append(
            f"| {r.get('phase', '')} | {'+'.join(r.get('learn', []))} | {'+'.join(r.get('active', []))} "
            f"| {r['return_mean']:.1f} ± {r['return_std']:.1f} | {auc} | {100 * r['repetition']:.1f}% "
            f"| {r['decisions']:.1f} of {r['episode_steps']:.0f} "
            f"| {_activity(r, 'decided_')} | {_activity(r, 'acted_')} |"
        )
    return "\n".join(lines)


def plot_curves(metrics_csv: Path, out_png: Path, title: str) -> None:
    """Evaluation return against base steps, one line per phase, with ±1 std over episodes."""
    with metrics_csv.open() as f:
        rows = list(csv.DictReader(f))
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for phase in dict.fromkeys(r["phase"] for r in rows):
        sel = [r for r in rows if r["phase"] == phase]
        x = [int(r["step"]) for r in sel]
        y = [float(r["return_mean"]) for r in sel]
        s = [float(r["return_std"]) for r in sel]
        line, = ax.plot(x, y, marker="o", ms=3, label=f"phase {int(phase) + 1}: {sel[0]['learn']} learns")
        ax.fill_between(x, [a - b for a, b in zip(y, s, strict=True)], [a + b for a, b in zip(y, s, strict=True)],
                        color=line.get_color(), alpha=0.2)
    ax.set_xlabel("environment steps in phase")
    ax.set_ylabel("evaluation return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def plot_episode(trace: Sequence[Any], layers: Sequence[str], out_png: Path, title: str) -> None:
    """One episode: above, when each layer decided (ticks) and contributed a non-zero part of the
    action (squares); below, the executed action per dimension."""
    steps = range(len(trace))
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(9, 2 + 0.4 * len(layers)), sharex=True, constrained_layout=True,
        gridspec_kw={"height_ratios": [max(1, len(layers)), 3]},
    )
    for row, name in enumerate(layers):
        decided = [t for t in steps if name in trace[t].decided]
        acted = [t for t in steps if name in trace[t].acted]
        top.scatter(decided, [row] * len(decided), marker="|", s=60, color="0.6", label="decided" if row == 0 else None)
        top.scatter(acted, [row + 0.25] * len(acted), marker="s", s=6, color=f"C{row}",
                    label="contributed" if row == 0 else None)
    top.set_yticks(range(len(layers)), layers)
    top.set_ylim(-0.6, len(layers) - 0.2)
    top.invert_yaxis()
    top.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize="small", ncols=2, frameon=False)
    top.set_title(title, loc="left")
    actions = [record.action for record in trace]
    for d in range(len(actions[0]) if actions else 0):
        bottom.step(list(steps), [a[d] for a in actions], where="post", lw=1, label=f"action[{d}]")
    bottom.set_xlabel("base step")
    bottom.set_ylabel("executed action")
    bottom.grid(alpha=0.3)
    if actions and len(actions[0]) <= 8:
        bottom.legend(loc="upper right", fontsize="small", ncols=4)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
