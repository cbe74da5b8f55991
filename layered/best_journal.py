"""A group's best weights beside its checkpoint, each seed's written only when its phase's best evaluation
changes. A seed's best weights are what a single run's checkpoint holds of its learners (networks, targets,
Adam moments), as large as the learners' own state: written whole at every checkpoint, 32 Hopper seeds'
doubled what each checkpoint wrote, though once learning settles a new best is seldom.

Each file (`layered.attachments`, in a `best/` folder beside the group's checkpoint) holds one seed's best
weights of its phase's learning layers; the checkpoint names the file of each seed (none before its
phase's first evaluation) with its checksum.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TypedDict

from layered.attachments import Attachment, Attachments, check_attachments
from layered.runstate import LoopState

BEST = "best weights"


class BestFiles(TypedDict):
    """A group checkpoint's part for the best weights: each seed's file (None where it has none yet), and how
    many files were ever written (the next file's number)."""

    files: list[Attachment | None]
    written: int


def best_folder(checkpoint: Path) -> Path:
    """Where the best weights of the group checkpointed at `checkpoint` are."""
    return checkpoint.parent / "best"


def _which(state: LoopState) -> tuple[int, int] | None:
    """Which best weights a seed holds: its phase and the step of that phase's best evaluation (None before
    the first)."""
    return (state.phase, state.curve[state.best_index()][0]) if state.curve else None


class BestJournal:
    """The files of a group's best weights in `folder`."""

    def __init__(self, folder: Path) -> None:
        self.files = Attachments(folder)
        self.saved = BestFiles(files=[], written=0)
        self._which: list[tuple[int, int] | None] = []  # what each seed's file holds

    def record(self, seeds: Sequence[int], states: Sequence[LoopState]) -> BestFiles:
        """Write the best weights of each seed (numbered `seeds[k]`) whose best changed since the last record; the
        part of the checkpoint about to be written."""
        files, written = list(self.saved["files"]) or [None] * len(states), self.saved["written"]
        which = self._which or [None] * len(states)
        for k, (seed, state) in enumerate(zip(seeds, states, strict=True)):
            now = _which(state)
            if now == which[k]:
                continue
            which[k] = now
            files[k] = None if which[k] is None else self.files.write(f"seed{seed}.{written:06d}.pt", BEST, state.best)
            written += files[k] is not None
        self.saved, self._which = BestFiles(files=files, written=written), which
        return self.saved

    def prune(self) -> None:
        """Once a checkpoint with the latest files is written: remove those neither it nor the one before names."""
        self.files.prune({attachment["file"] for attachment in self.saved["files"] if attachment is not None})

    def load(self, saved: BestFiles, states: Sequence[LoopState]) -> None:
        """Give each seed's state the best weights that a checkpoint's `saved` names; the next record goes on from
        there."""
        for state, attachment in zip(states, saved["files"], strict=True):
            state.best = {} if attachment is None else self.files.load(attachment, BEST)
        self.saved, self._which = saved, [_which(state) for state in states]
        self.files.restore({attachment["file"] for attachment in saved["files"] if attachment is not None})

    def clear(self) -> None:
        """Remove every file (a group starting over, or one that has finished)."""
        self.files.clear()
        self.saved, self._which = BestFiles(files=[], written=0), []


def check_best(folder: Path, saved: BestFiles) -> None:
    """Refuse (CheckpointError) the checkpoint whose part `saved` is if a file it names is missing or damaged."""
    check_attachments(folder, [attachment for attachment in saved["files"] if attachment is not None], BEST)

