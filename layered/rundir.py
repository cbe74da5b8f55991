"""The run directory's identity: the resolved recipe and how the run was started, written before
training; the rule that a directory holding a run is never silently started over; and one writer at
a time, by an OS lock that dies with the process holding it."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import socket
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from layered.checkpoint import previous, unfinished_write, write_atomically
from layered.errors import BadInput
from layered.summary import PHASES_FILE

LOCK_FILE = ".lock"
_HELD: set[Path] = set()  # the run directories this process writes
RUN_CHECKPOINT = Path("checkpoints") / "run.pt"
"""A single run's training checkpoint, in its directory (the one before it beside it, `checkpoint.previous`)."""
RUN_FILES = ("recipe.toml", "run.json", "metrics.csv", "episodes.csv", PHASES_FILE, "results.json", "results.md",
             "curves.png", "checkpoints", "eval", "train.log", LOCK_FILE)


class RunDirError(BadInput, ValueError):
    """A run directory that cannot be used as asked (it holds another run, or no run)."""


@dataclass(frozen=True)
class RunInfo:
    """How a run was started, besides its recipe: what `layered resume` needs to continue it."""

    label: str
    max_steps: int | None
    plugins: tuple[str, ...] = ()
    group: tuple[int, ...] = ()  # the seeds trained together in one process with this one (layered.group)
    changes: tuple[dict[str, Any], ...] = ()  # settings changed on resuming (`layered resume --set`), in order
    threads: int | None = None  # the torch threads it computed with (an evaluation's last digits depend on them)


def steps_option(max_steps: int | None) -> str:
    """How a run's step cap was asked for on the command line: `--steps 2000`, or `no --steps`."""
    return "no --steps" if max_steps is None else f"--steps {max_steps}"


def check_same_steps(where: Path, started: int | None, asked: int | None, what: str = "run") -> None:
    """Refuse to resume the run (or group) in `where` with another `--steps` than the one it was `started` with
    (`asked` None: not given, so nothing to check)."""
    if asked is not None and asked != started:
        raise RunDirError(f"{where}: the {what} was started with {steps_option(started)}, not {steps_option(asked)}")


def no_checkpoint_to_change(where: Path, what: str = "run") -> RunDirError:
    """The refusal of settings changed on resuming a run (or group) that stopped before its first checkpoint."""
    return RunDirError(f"{where}: the {what} has no checkpoint to continue from with other settings; train it again "
                       "with --force and the settings in the recipe or on the command line")


def has_progress(run_dir: Path) -> bool:
    """Whether the directory holds a run with something to lose: a checkpoint or results."""
    run_state = run_dir / RUN_CHECKPOINT
    return any(p.exists() for p in (run_dir / "results.json", run_state, previous(run_state)))


@contextmanager
def writing(run_dir: Path) -> Iterator[None]:
    """Hold the run directory's lock while writing it (creating the directory): a second writer is
    refused, naming the first. The lock is the operating system's, released when its holder ends,
    however it ends, so a killed run never leaves a stale one."""
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 500).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise RunDirError(f"{run_dir} is being written by {holder}; wait for it to end, or stop it") from None
    try:
        os.ftruncate(fd, 0)
        command = " ".join(["layered", *sys.argv[1:]])
        command = command if len(command) <= 200 else f"{command[:120]} ... {command[-75:]}"  # --out is last
        os.write(fd, f"process {os.getpid()} on {socket.gethostname()} ({command})".encode())
        _HELD.add(run_dir.resolve())
        tidy_unfinished_writes(run_dir)
        yield
    finally:
        _HELD.discard(run_dir.resolve())
        os.close(fd)  # releases the lock


def writer(run_dir: Path) -> str | None:
    """Which other process is writing the run directory now (as its lock names it), or None; takes
    nothing from it."""
    if run_dir.resolve() in _HELD:
        return None
    try:
        fd = os.open(run_dir / LOCK_FILE, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return os.read(fd, 500).decode(errors="replace").strip() or "another process"
    finally:
        os.close(fd)
    return None


def warn_if_being_written(run_dir: Path) -> None:
    """Say, in one line, that a run read for evaluation or export is still being trained: its layer
    checkpoints are whole (each written atomically) but of the phases finished so far."""
    if (holder := writer(run_dir)) is not None:
        print(f"layered: note: {run_dir} is being trained by {holder}; using its checkpoints as they stand",
              file=sys.stderr)


def foreign_files(run_dir: Path) -> list[str]:
    """The names in a directory that are not a run's files (nor what a write of one cut short left)."""
    return sorted(p.name for p in run_dir.iterdir() if p.name not in RUN_FILES and
                  unfinished_write(p.name) not in RUN_FILES)


def tidy_unfinished_writes(run_dir: Path) -> None:
    """Remove what writes cut short (a process killed while writing a file) left in the run's directory and its
    checkpoints/: temporary files, each beside the intact file it was to replace. Only the run's writer does it."""
    for folder, kept in ((run_dir, RUN_FILES), (run_dir / "checkpoints", None)):
        for path in folder.glob(".*") if folder.is_dir() else ():
            if (name := unfinished_write(path.name)) is not None and (kept is None or name in kept):
                path.unlink(missing_ok=True)


def check_new_run_dir(run_dir: Path) -> None:
    """Refuse a directory that is being written, holds a run with progress, or files that are not a run's."""
    if not run_dir.exists():
        return
    if not run_dir.is_dir():
        raise RunDirError(f"{run_dir} is a file, not a directory")
    if (holder := writer(run_dir)) is not None:
        raise RunDirError(f"{run_dir} is being written by {holder}; wait for it to end, or stop it")
    if (run_dir / "results.json").exists():
        raise RunDirError(f"{run_dir} holds a finished run; choose another --out, or --force to start over")
    if has_progress(run_dir):
        raise RunDirError(f"{run_dir} holds a stopped run; continue it with `layered resume {run_dir}`, "
                          "or --force to start over")
    if foreign := foreign_files(run_dir):
        raise RunDirError(f"{run_dir} holds files that are not a run's ({', '.join(foreign[:3])}); "
                          "choose another --out")


def refuse_group_seed(run_dir: Path) -> None:
    """Refuse a single run in a directory where a seed of a group was trained: the group's resume, evaluation and
    report take its seeds from their run.json, and one seed replaced would leave the others unfinishable."""
    if (run_dir / "run.json").exists() and (group := read_run_info(run_dir).group):
        raise RunDirError(f"{run_dir} holds a seed of the group of seeds {list(group)} in {run_dir.parent}; a single "
                          f"run cannot take its place (continue the group with `layered resume {run_dir.parent}`, "
                          "or train the run in a directory of its own)")


def clear_run_dir(run_dir: Path) -> None:
    """Remove a run's own files (for --force), under the run's lock: refused before anything is
    removed where another process writes the run or where the directory holds files of another kind."""
    if foreign := foreign_files(run_dir):
        raise RunDirError(f"{run_dir} holds files that are not a run's ({', '.join(foreign[:3])}); --force "
                          "starts a run over only in a directory of its own: choose another --out")
    with writing(run_dir):  # (which removes what writes cut short left)
        for name in RUN_FILES:
            path = run_dir / name
            if path.is_dir():
                shutil.rmtree(path)
            elif name != LOCK_FILE:
                path.unlink(missing_ok=True)


def prepare_run_dir(run_dir: Path, recipe_text: str, info: RunInfo, resume: bool,
                    precision: Mapping[str, str] | None = None) -> None:
    """Create the run directory with its recipe and run.json, which records what each layer's updates compute in
    (`precision`: `precision = "auto"` depends on the machine); a run stopped before its first checkpoint lost
    nothing and starts over. Without `resume`, a run with progress is refused."""
    if not resume:
        check_new_run_dir(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    if resume and has_progress(run_dir):
        return
    write_atomically(run_dir / "recipe.toml", recipe_text)
    write_atomically(run_dir / "run.json", json.dumps(
        {"label": info.label, "max_steps": info.max_steps, "plugins": list(info.plugins), "group": list(info.group)}
        | ({"threads": info.threads} if info.threads else {}) | ({"precision": dict(precision)} if precision else {}),
        indent=2))


def read_run_info(run_dir: Path) -> RunInfo:
    """How the run in `run_dir` was started."""
    path = run_dir / "run.json"
    if not run_dir.exists():
        raise RunDirError(f"{run_dir}: no such directory")
    if not (run_dir / "recipe.toml").is_file() or not path.is_file():
        raise RunDirError(f"{run_dir} is not a run directory (no recipe.toml and run.json){_not_a_run_hint(run_dir)}")
    try:
        data = json.loads(path.read_text())
        return RunInfo(str(data["label"]), data["max_steps"], tuple(data["plugins"]), tuple(data.get("group", ())),
                       tuple(data.get("changes", ())), data.get("threads"))
    except (ValueError, KeyError, TypeError) as e:
        raise RunDirError(f"{path} is damaged ({e.__class__.__name__}: {e})") from None


def _not_a_run_hint(directory: Path) -> str:
    """What to do with a directory that is not a run's: name the runs it holds (a group's seeds, a sweep's), or say
    that a run stopped before it wrote anything starts again."""
    runs = sorted((str(p.parent.relative_to(directory)) for p in directory.rglob("run.json")),
                  key=lambda name: (len(name), name))
    if runs:
        named = ", ".join(runs[:4]) + (f" and {len(runs) - 4} more" if len(runs) > 4 else "")
        return f"; it holds the runs {named}: name one of them ({directory / runs[0]})"
    if not directory.is_dir() or not any(p.name in RUN_FILES for p in directory.iterdir()):
        return "; a run stopped before it wrote anything starts again with `layered train`"
    return ""


def record_change(run_dir: Path, recipe_text: str, change: dict[str, Any]) -> None:
    """Make `recipe_text` the run's recipe and add `change` (where and what was changed) to run.json."""
    data = json.loads((run_dir / "run.json").read_text())
    data["changes"] = [*data.get("changes", []), change]
    write_atomically(run_dir / "recipe.toml", recipe_text)
    write_atomically(run_dir / "run.json", json.dumps(data, indent=2))


def run_plugins(run_dir: Path) -> list[str]:
    """The plugins a run was trained with."""
    return list(read_run_info(run_dir).plugins)
