"""Where an unfinished run stands (one training now, or stopped): the phase under way at its last checkpoint and
the weights of that phase's learning layers at their best evaluation so far, read from the run's checkpoint or
its group's. What `layered eval` evaluates before a run has finished.

A reader never changes a file here: the run's writer may be at work beside it, so a checkpoint that cannot be
read is passed over for the previous one, never removed (`layered.checkpoint.load_latest` is the writer's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from layered.attachments import Attachments
from layered.best_journal import BEST, best_folder
from layered.checkpoint import CheckpointError, load_checkpoint, previous
from layered.group_state import GROUP_CHECKPOINT, group_dir
from layered.rundir import RUN_CHECKPOINT, RunDirError
from layered.runstate import LoopState


@dataclass(frozen=True)
class Standing:
    """An unfinished run at its last checkpoint: phase `phase` at step `step`, and its learning layers' weights
    at their best evaluation so far (`best`; that evaluation's step and mean return). At a phase boundary (no
    evaluation of phase `phase` yet) `best` is empty: the stack is the one the phase before ended with."""

    phase: int
    step: int
    best: dict[str, dict[str, Any]]
    best_step: int = 0
    best_return: float = 0.0

    @property
    def stack_phase(self) -> int:
        """The phase whose stack there is to evaluate: the one under way, or at a boundary the one before."""
        return self.phase if self.best else self.phase - 1

    @property
    def folder(self) -> str:
        """Where, under the run's `eval/`, evaluations of these weights go: apart from a finished run's, which
        `layered report` reads."""
        at = f"best-{self.best_step}" if self.best else "end"
        return f"unfinished/phase{self.stack_phase}-{at}"


def standing(run_dir: Path, seed: int) -> Standing:
    """Where the unfinished run in `run_dir` (of recipe seed `seed`) stands, from its newest readable checkpoint
    (a single run's `checkpoints/run.pt`, or its group's `group.pt` and best weights)."""
    directory = group_dir(run_dir)
    if directory is None:
        at = _newest(run_dir / RUN_CHECKPOINT, "run",
                     lambda saved: _at(LoopState.from_json(saved["loop"]), saved["best"]))
    else:
        path = directory / GROUP_CHECKPOINT

        def of_seed(saved: dict[str, Any]) -> Standing:
            k = saved["seeds"].index(seed)
            attachment = saved["best"]["files"][k]
            best = {} if attachment is None else Attachments(best_folder(path)).load(attachment, BEST)
            return _at(LoopState.from_json(saved["states"][k]), best)

        at = _newest(path, "group", of_seed)
    if at is None or at.stack_phase < 0:
        raise RunDirError(f"{run_dir} has not finished and has no checkpoint yet: evaluate it after its first")
    return at


def _newest(path: Path, kind: str, read: Callable[[dict[str, Any]], Standing]) -> Standing | None:
    """`read` of the checkpoint at `path`, or of the one before where that one cannot be read whole; None where
    there is neither."""
    problems = []
    for candidate in (path, previous(path)):
        if candidate.exists():
            try:
                return read(load_checkpoint(candidate, kind))
            except CheckpointError as e:
                problems.append(str(e))
    if problems:
        raise CheckpointError("; ".join(problems))
    return None


def _at(state: LoopState, best: dict[str, dict[str, Any]]) -> Standing:
    """The standing that a run's loop state `state` and its best weights `best` describe."""
    if not state.curve:
        return Standing(state.phase, 0, {})
    step, evaluation = state.curve[state.best_index()]
    return Standing(state.phase, state.step, best, step, evaluation.return_mean)
