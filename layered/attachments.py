"""Files that a checkpoint names beside itself, so that it need not hold what has not changed since the
checkpoint before (replay segments, a group's best weights). Each is written once, atomically and
checksummed, and named in the checkpoint with its checksum, so that one rewritten after a crash is never
taken for the one the checkpoint was taken with; a file that neither the newest nor the previous
checkpoint names is removed once the newest is written.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypedDict

from layered.checkpoint import CheckpointError, load_checkpoint, save_checkpoint, verified_digest


class Attachment(TypedDict):
    """How a checkpoint names a file beside it."""

    file: str
    digest: str


class Attachments:
    """The files in `folder` that the checkpoints of one run (or group) name."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.kept: set[str] = set()  # what the checkpoint on disk names: the previous one after the next

    def write(self, file: str, kind: str, state: dict[str, Any]) -> Attachment:
        """Write `state` as the file `file` (a checkpoint file of `kind`); how a checkpoint names it."""
        return {"file": file, "digest": save_checkpoint(self.folder / file, kind, state)}

    def load(self, attachment: Attachment, kind: str) -> dict[str, Any]:
        """The state written as `attachment`."""
        return load_checkpoint(self.folder / attachment["file"], kind)

    def prune(self, named: set[str]) -> None:
        """Once a checkpoint that names the files `named` is written: remove the files that neither it nor the one
        before it names (those of checkpoints replaced, and any a crash left unfinished)."""
        for path in self.folder.glob("*"):
            if path.name not in named | self.kept:
                path.unlink(missing_ok=True)
        self.kept = set(named)

    def restore(self, named: set[str]) -> None:
        """Go on from a checkpoint that names the files `named`."""
        self.kept = set(named)

    def clear(self) -> None:
        """Remove every file (a group starting over, or one that has finished)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        self.kept = set()


def check_attachments(folder: Path, attachments: Iterable[Attachment], what: str) -> None:
    """Refuse (CheckpointError) a checkpoint if a file it names in `folder` is missing, damaged or not the one
    it was written with; `what` says what such a file is ("replay segment")."""
    for attachment in attachments:
        if verified_digest(folder / attachment["file"]) != attachment["digest"]:
            raise CheckpointError(f"{folder / attachment['file']}: not the {what} the checkpoint was taken with")
