"""The run directory's identity: the resolved recipe and how the run was started, written before
training, and the rule that a directory holding a run is never silently started over."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

from layered.checkpoint import previous, write_atomically

RUN_FILES = ("recipe.toml", "run.json", "metrics.csv", "episodes.csv", "results.json", "results.md", "curves.png",
             "checkpoints", "eval", "train.log")


class RunDirError(ValueError):
    """A run directory that cannot be used as asked (it holds another run, or no run)."""


@dataclass(frozen=True)
class RunInfo:
    """How a run was started, besides its recipe: what `layered resume` needs to continue it."""

    label: str
    max_steps: int | None
    plugins: tuple[str, ...] = ()


def has_progress(run_dir: Path) -> bool:
    """Whether the directory holds a run with something to lose: a checkpoint or results."""
    run_state = run_dir / "checkpoints" / "run.pt"
    return any(p.exists() for p in (run_dir / "results.json", run_state, previous(run_state)))


def check_new_run_dir(run_dir: Path) -> None:
    """Refuse a directory that holds a run with progress, or files that are not a run's."""
    if not run_dir.exists():
        return
    if not run_dir.is_dir():
        raise RunDirError(f"{run_dir} is a file, not a directory")
    if (run_dir / "results.json").exists():
        raise RunDirError(f"{run_dir} holds a finished run; choose another --out, or --force to start over")
    if has_progress(run_dir):
        raise RunDirError(f"{run_dir} holds a stopped run; continue it with `layered resume {run_dir}`, "
                          "or --force to start over")
    foreign = sorted(p.name for p in run_dir.iterdir() if p.name not in RUN_FILES)
    if foreign:
        raise RunDirError(f"{run_dir} holds files that are not a run's ({', '.join(foreign[:3])}); "
                          "choose another --out")


def clear_run_dir(run_dir: Path) -> None:
    """Remove a run's own files (for --force), leaving anything else in the directory."""
    for name in RUN_FILES:
        path = run_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


def prepare_run_dir(run_dir: Path, recipe_text: str, info: RunInfo, resume: bool) -> None:
    """Create the run directory with its recipe and run.json; a run stopped before its first
    checkpoint lost nothing and starts over. Without `resume`, a run with progress is refused."""
    if not resume:
        check_new_run_dir(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    if resume and has_progress(run_dir):
        return
    write_atomically(run_dir / "recipe.toml", recipe_text)
    write_atomically(run_dir / "run.json", json.dumps(
        {"label": info.label, "max_steps": info.max_steps, "plugins": list(info.plugins)}, indent=2))


def read_run_info(run_dir: Path) -> RunInfo:
    """How the run in `run_dir` was started."""
    path = run_dir / "run.json"
    if not (run_dir / "recipe.toml").is_file() or not path.is_file():
        empty = not run_dir.is_dir() or not any(p.name in RUN_FILES for p in run_dir.iterdir())
        hint = "; a run stopped before it wrote anything starts again with `layered train`" if empty else ""
        raise RunDirError(f"{run_dir} is not a run directory (no recipe.toml and run.json){hint}")
    try:
        data = json.loads(path.read_text())
        return RunInfo(str(data["label"]), data["max_steps"], tuple(data["plugins"]))
    except (ValueError, KeyError, TypeError) as e:
        raise RunDirError(f"{path} is damaged ({e.__class__.__name__}: {e})") from None


def run_plugins(run_dir: Path) -> list[str]:
    """The plugins a run was trained with."""
    return list(read_run_info(run_dir).plugins)
