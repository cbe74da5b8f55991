"""Where an unfinished run stands (one training now, or stopped): the phase under way at its last checkpoint, the
weights of that phase's learning layers at their best evaluation so far, and their learner states at that
checkpoint, read from the run's checkpoint or its group's. What `layered eval` evaluates before a run has finished.

A reader never changes a file here: the run's writer may be at work beside it, so a checkpoint that cannot be
read is passed over for the previous one, and the writer's unfinished files are left alone (`tidy=False`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
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
    """An unfinished run at its last checkpoint: phase `phase` at step `step`, its learning layers' weights at their
    best evaluation so far (`best`; that evaluation's step and mean return), and their learner states there
    (`latest`, as `resume_state` returned them: of a group's seed, the group's, in which the seed is row `row` of
    `rows`). At a phase boundary (no evaluation of phase `phase` yet) `best` is empty: the stack is the one the
    phase before ended with."""

    phase: int
    step: int
    best: dict[str, dict[str, Any]]
    best_step: int = 0
    best_return: float = 0.0
    latest: dict[str, dict[str, Any]] = field(default_factory=dict)
    row: int | None = None
    rows: int = 1

    @property
    def stack_phase(self) -> int:
        """The phase whose stack there is to evaluate: the one under way, or at a boundary the one before."""
        return self.phase if self.best else self.phase - 1

    def folder(self, latest: bool = False) -> str:
        """Where, under the run's `eval/`, evaluations of the best weights so far (or with `latest`, of the weights at
        the checkpoint) go: apart from a finished run's, which `layered report` reads."""
        at = ("end" if not self.best else f"step-{self.step}" if latest else f"best-{self.best_step}")
        return f"unfinished/phase{self.stack_phase}-{at}"


def standing(run_dir: Path, seed: int) -> Standing:
    """Where the unfinished run in `run_dir` (of recipe seed `seed`) stands, from its newest readable checkpoint
    (a single run's `checkpoints/run.pt`, or its group's `group.pt` and the seed's best weights)."""
    at = None
    directory = group_dir(run_dir)
    if directory is None:
        saved = load_latest(run_dir / RUN_CHECKPOINT, "run", tidy=False)
        if saved is not None:
            at = _at(LoopState.from_json(saved["loop"]), saved["best"], saved["learners"])
    else:
        files = Attachments(best_folder(directory / GROUP_CHECKPOINT))

        def best_file(saved: dict[str, Any]) -> Attachment | None:
            return saved["best"]["files"][saved["seeds"].index(seed)]

        def check(saved: dict[str, Any]) -> None:  # (a checkpoint whose file of this seed is gone counts as unreadable)
            if (attachment := best_file(saved)) is not None:
                check_attachments(files.folder, [attachment], BEST)

        saved = load_latest(directory / GROUP_CHECKPOINT, "group", check, tidy=False)
        if saved is not None:
            attachment, row = best_file(saved), saved["seeds"].index(seed)
            best = {} if attachment is None else files.load(attachment, BEST)
            at = _at(LoopState.from_json(saved["states"][row]), best, saved["learners"], row, len(saved["seeds"]))
    if at is None or at.stack_phase < 0:
        raise RunDirError(f"{run_dir} has not finished and has no checkpoint yet: evaluate it after its first")
    return at


def _at(state: LoopState, best: dict[str, dict[str, Any]], learners: dict[str, dict[str, Any]], row: int | None = None,
        rows: int = 1) -> Standing:
    """The standing that a run's loop state `state`, its best weights `best` and its checkpoint's learner states
    `learners` (of a group: row `row` of `rows`) describe."""
    if not state.curve:
        return Standing(state.phase, 0, {})
    step, evaluation = state.curve[state.best_index()]
    latest = {name: learners[name] for name in best}  # (the layers the phase learns)
    return Standing(state.phase, state.step, best, step, evaluation.return_mean, latest, row, rows)
