"""A group's checkpoint: where K seeds training together stand, saved at any step and continued exactly.

A single run checkpoints at an episode end, where no simulator state needs keeping. A group's seeds end
their episodes at different steps, so its checkpoint holds every environment's simulator state
(`layered.envs.snapshot_env`) beside the rules' rows, each layer's stacked learners, the phase's open
transitions and each seed's loop state. It is one file, `group.pt`, in the group's directory (the seeds'
run directories are its `seed<k>` folders), written atomically beside its previous one; the replay buffers'
rows are in the directory's `replay/` folder, each checkpoint adding what was stored since the last
(layered.replay_journal), and each seed's best weights in its `best/` folder, written when they change
(layered.best_journal).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from layered.best_journal import BestFiles, BestJournal, best_folder, check_best
from layered.checkpoint import CheckpointError, load_latest, previous, save_checkpoint
from layered.checkpoint_writer import as_arrays, host_copy
from layered.replay_journal import Manifest, ReplayJournal, check_segments, replay_folder
from layered.rundir import RunDirError, RunInfo, check_new_run_dir, clear_run_dir, read_run_info, steps_option
from layered.runstate import LoopState, digested, recipe_differences, recipe_digest

GROUP_CHECKPOINT = "group.pt"


@dataclass
class Pending:
    """Per row, a learning layer's latest decision and what has followed it: its next transitions."""

    seen: np.ndarray
    output: np.ndarray
    reward: np.ndarray
    elapsed: np.ndarray
    open: np.ndarray  # whether the row has decided this episode
    repeats: bool  # whether the layer may repeat its decisions, which then keep their path
    period_reward: np.ndarray  # a repeating layer's: the reward of the period under way
    period_steps: np.ndarray
    path: list[list[tuple[np.ndarray, float, int]]]  # a repeating layer's, per row: per period of its repeat

    @classmethod
    def empty(cls, rows: int, obs: int, size: int, repeats: bool) -> Pending:
        return cls(np.zeros((rows, obs), np.float32), np.zeros((rows, size), np.float32), np.zeros(rows),
                   np.zeros(rows, np.int64), np.zeros(rows, bool), repeats, np.zeros(rows), np.zeros(rows, np.int64),
                   [[] for _ in range(rows)])

    def decide(self, rows: np.ndarray, seen: np.ndarray) -> None:
        """New decisions in the `rows` (a mask), which saw `seen`: nothing has followed them yet."""
        self.seen[rows], self.open[rows] = seen, True
        self.reward[rows], self.elapsed[rows] = 0.0, 0
        if self.repeats:
            self.period_reward[rows], self.period_steps[rows] = 0.0, 0
            for k in np.flatnonzero(rows).tolist():
                self.path[k] = []

    def accrue(self, share: np.ndarray) -> None:
        """Book one base step into the open decisions: its `share` of the reward and one step elapsed (for a
        repeating layer, into the period under way too)."""
        self.reward += np.where(self.open, share, 0.0)
        self.elapsed += self.open
        if self.repeats:
            self.period_reward += np.where(self.open, share, 0.0)
            self.period_steps += self.open

    def end_periods(self, ends: np.ndarray, seen: np.ndarray, units: Callable[[int], int]) -> None:
        """A repeating layer's periods ended in the `ends` rows (open ones): (what it sees, the period's
        reward, its discount `units` for the period's steps) joins each row's path."""
        for k in np.flatnonzero(ends).tolist():
            self.path[k].append((seen[k].copy(), float(self.period_reward[k]), units(int(self.period_steps[k]))))
        self.period_reward[ends], self.period_steps[ends] = 0.0, 0


@dataclass
class PhaseLoop:
    """Where a group's phase stands besides its learners, rules, environments and seeds' loop states."""

    step: int
    pending: dict[int, Pending]  # per learning layer's index
    returns: np.ndarray  # [K] of the episodes under way
    lengths: np.ndarray


@dataclass
class GroupCheckpoint:
    """A group's training state as loaded: the learners' part is handed to them, the rest to the loop."""

    states: list[LoopState]
    loop: PhaseLoop
    rules: dict[str, Any]
    envs: list[dict[str, Any]]
    obs: np.ndarray
    learners: dict[str, dict[str, Any]]
    torch_rng: torch.Tensor
    replays: dict[str, Manifest]  # per replay buffer (`<layer>.<part>`), its segments
    best: BestFiles  # each seed's best weights (loaded into its state by `BestJournal.load`)


def group_dir(run_dir: Path) -> Path | None:
    """The directory of the group that `run_dir` (the group's own directory, or one of its seeds') belongs
    to; None for a single run's directory."""
    if (run_dir / "run.json").exists():
        return run_dir.parent if read_run_info(run_dir).group else None
    seeds = sorted(run_dir.glob("seed*/run.json"))
    return run_dir if seeds and read_run_info(seeds[0].parent).group else None


def group_info(directory: Path) -> RunInfo:
    """How the group in `directory` was started (as each of its seeds' run.json says)."""
    runs = sorted(directory.glob("seed*/run.json"))
    if not runs:
        raise RunDirError(f"{directory} holds no group of seeds (no seed<k>/run.json)")
    return read_run_info(runs[0].parent)


def seed_dirs(directory: Path, seeds: Sequence[int]) -> list[Path]:
    """The run directories of a group's seeds."""
    return [directory / f"seed{seed}" for seed in seeds]


def group_snapshot(seeds: list[int], recipes: list[dict[str, Any]], max_steps: int | None,
                   checkpoint: GroupCheckpoint, beside: bool = True) -> dict[str, Any]:
    """The group's checkpoint as its file holds it, with its seeds' resolved `recipes` (what resuming must match);
    for a write `beside` training, its tensors copied to the host (`host_copy`), so that the group can go on while
    it is written."""
    loop = checkpoint.loop
    return host_copy({
        "seeds": list(seeds), "recipe_digests": [recipe_digest(recipe) for recipe in recipes],
        "recipes": [json.dumps(digested(recipe), sort_keys=True) for recipe in recipes], "max_steps": max_steps,
        "states": [state.to_json() for state in checkpoint.states], "best": checkpoint.best,
        "loop": {"step": loop.step, "pending": {str(i): asdict(p) for i, p in loop.pending.items()},
                 "returns": loop.returns, "lengths": loop.lengths},
        "rules": checkpoint.rules, "envs": checkpoint.envs, "obs": checkpoint.obs,
        "learners": checkpoint.learners, "torch_rng": checkpoint.torch_rng, "replays": checkpoint.replays,
    }, tensors=beside)


def save_group(directory: Path, snapshot: dict[str, Any]) -> None:
    """Write the group's checkpoint (`group_snapshot`); the one it replaces is kept as its previous."""
    save_checkpoint(directory / GROUP_CHECKPOINT, "group", snapshot, keep_previous=True)


def load_group(directory: Path, seeds: list[int], recipes: list[dict[str, Any]], max_steps: int | None,
               before: Sequence[str | None] = ()) -> GroupCheckpoint | None:
    """The group's newest usable checkpoint (one whose replay segments and best weights are all there, undamaged),
    or None if it has none; refused, in one line, when it was taken for other seeds, recipes (`resolved`, naming
    what differs) or `--steps`.
    A seed's checkpoint may also have been taken with the recipe of digest `before[k]` (its settings changed
    since, see `layered.runs.changed_from`)."""
    path = directory / GROUP_CHECKPOINT

    def check(saved: dict[str, Any]) -> None:
        if not isinstance(saved.get("best"), dict):
            raise CheckpointError(f"{path}: written by a development version of layered that kept the best weights "
                                  "in the checkpoint; start the group again with --force")
        check_segments(replay_folder(path), saved["replays"])
        check_best(best_folder(path), saved["best"])

    saved = load_latest(path, "group", check)
    if saved is None:
        return None
    if saved["seeds"] != list(seeds):
        raise CheckpointError(f"{directory}: the group's checkpoint is of seeds {saved['seeds']}, not {list(seeds)}")
    before = list(before) or [None] * len(seeds)
    digests = [recipe_digest(recipe) for recipe in recipes]
    changed = [k for k, (a, b, c) in enumerate(zip(saved["recipe_digests"], digests, before, strict=True))
               if a not in (b, c)]
    if changed:
        k = changed[0]
        what = ("" if "recipes" not in saved else  # (a checkpoint of an earlier version holds their digests alone)
                " (" + ", ".join(recipe_differences(json.loads(saved["recipes"][k]), digested(recipes[k]))) + ")")
        raise CheckpointError(f"{directory}: the recipe of seeds {[seeds[k] for k in changed]} differs from the one "
                              f"the group's checkpoint was taken with{what}")
    if saved["max_steps"] != max_steps:
        raise CheckpointError(f"{directory}: the group was started with {steps_option(saved['max_steps'])}, not "
                              f"{steps_option(max_steps)}")
    states = [LoopState.from_json(text) for text in saved["states"]]
    loop = saved["loop"]
    pending = {int(i): Pending(**as_arrays(p)) for i, p in loop["pending"].items()}
    return GroupCheckpoint(states, PhaseLoop(int(loop["step"]), pending, as_arrays(loop["returns"]),
                                             as_arrays(loop["lengths"])),
                           as_arrays(saved["rules"]), as_arrays(saved["envs"]), as_arrays(saved["obs"]),
                           saved["learners"], saved["torch_rng"], saved["replays"], saved["best"])


def has_group_checkpoint(directory: Path) -> bool:
    """Whether a stopped group waits in `directory` (its newest checkpoint, or the one before)."""
    return (directory / GROUP_CHECKPOINT).exists() or previous(directory / GROUP_CHECKPOINT).exists()


def check_new_group(directory: Path, outs: Sequence[Path]) -> None:
    """Refuse to start a group over seeds' run directories that hold runs, where a stopped group waits, or where
    `check_group_directory` refuses it."""
    check_group_directory(directory, outs)
    for out in outs:
        check_new_run_dir(out)
    if has_group_checkpoint(directory):
        raise RunDirError(f"{directory} holds a stopped group; continue it with `layered resume {directory}`, "
                          "or --force to start over")


def check_group_directory(directory: Path, outs: Sequence[Path]) -> None:
    """Refuse a group's `directory` where it holds a run of its own or the seeds of another group (a directory holds
    one group: its resume, evaluation and report take the group its seeds' run.json name), --force or not."""
    if any((directory / name).exists() for name in ("run.json", "recipe.toml")):
        raise RunDirError(f"{directory} holds a run of its own; a group's seeds go in a directory of their own: choose "
                          "another --out")
    mine = {out.name for out in outs}
    others = sorted((p.parent.name for p in directory.glob("*/run.json") if p.parent.name not in mine),
                    key=lambda name: (len(name), name))
    if others:
        whose = "of another group" if all(re.fullmatch(r"seed\d+", name) for name in others) else "of other runs"
        raise RunDirError(f"{directory} holds {', '.join(others[:3])}{', ...' * (len(others) > 3)} {whose}; a "
                          "directory holds one group: choose another --out")


def clear_group_and_seeds(directory: Path, outs: Sequence[Path]) -> None:
    """Start a group over (`--force`), in a directory `check_group_directory` took: its seeds' run directories and its
    checkpoint removed (a seed's directory holding files of another kind is refused, as `clear_run_dir` refuses it)."""
    for out in outs:
        if out.is_dir():
            clear_run_dir(out)
    clear_group(directory)


def clear_group(directory: Path) -> None:
    """Remove a group's checkpoints (a group starting over, or one whose seeds have all written their results)."""
    for path in (directory / GROUP_CHECKPOINT, previous(directory / GROUP_CHECKPOINT)):
        path.unlink(missing_ok=True)
    ReplayJournal(replay_folder(directory / GROUP_CHECKPOINT)).clear()
    BestJournal(best_folder(directory / GROUP_CHECKPOINT)).clear()
