"""Where an unfinished run stands (one training now, or stopped): the phase under way at its last checkpoint and
the weights of that phase's learning layers at their best evaluation so far, read from the run's checkpoint or
its group's. What `layered eval` evaluates before a run has finished.

A reader never changes a file here: the run's writer may be at work beside it, so a checkpoint that cannot be
read is passed over for the previous one, and the writer's unfinished files are left alone (`tidy=False`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from layered.attachments import Attachment, Attachments, check_attachments
from layered.best_journal import BEST, best_folder
from layered.checkpoint import load_latest
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
    (a single run's `checkpoints/run.pt`, or its group's `group.pt` and the seed's best weights)."""
    at = None
    directory = group_dir(run_dir)
    if directory is None:
        saved = load_latest(run_dir / RUN_CHECKPOINT, "run", tidy=False)
        if saved is not None:
            at = _at(LoopState.from_json(saved["loop"]), saved["best"])
    else:
        files = Attachments(best_folder(directory / GROUP_CHECKPOINT))

        def best_file(saved: dict[str, Any]) -> Attachment | None:
            return saved["best"]["files"][saved["seeds"].index(seed)]

        def check(saved: dict[str, Any]) -> None:  # (a checkpoint whose file of this seed is gone counts as unreadable)
            if (attachment := best_file(saved)) is not None:
                check_attachments(files.folder, [attachment], BEST)

        saved = load_latest(directory / GROUP_CHECKPOINT, "group", check, tidy=False)
        if saved is not None:
            attachment = best_file(saved)
            at = _at(LoopState.from_json(saved["states"][saved["seeds"].index(seed)]),
                     {} if attachment is None else files.load(attachment, BEST))
    if at is None or at.stack_phase < 0:
        raise RunDirError(f"{run_dir} has not finished and has no checkpoint yet: evaluate it after its first")
    return at


def _at(state: LoopState, best: dict[str, dict[str, Any]]) -> Standing:
    """The standing that a run's loop state `state` and its best weights `best` describe."""
    if not state.curve:
        return Standing(state.phase, 0, {})
    step, evaluation = state.curve[state.best_index()]
    return Standing(state.phase, state.step, best, step, evaluation.return_mean)
