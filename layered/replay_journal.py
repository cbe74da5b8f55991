"""A run's replay buffers on disk as segments, so that a checkpoint writes what was stored since the last
one, not the whole buffer: at the paper's 1M transitions per seed, one Hopper seed holds 112 MB of replay
and a group of 32 holds 3.6 GB, which a checkpoint per evaluation would otherwise write again each time.

A segment is a file of its own (`layered.attachments`) in a `replay/` folder beside the run's (or the
group's) checkpoint, which holds a manifest per buffer: its stored counts and its segments, each with its
checksum. Segments whose rows the ring has all overwritten leave the manifest.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from layered.attachments import Attachments, check_attachments

Manifest = dict[str, Any]
"""One buffer's part of a checkpoint: `stored` (per seed), `written` (segments ever written) and `segments`
(each a dict of `file`, `digest`, and per seed the index of its `first` row and the row `counts`)."""

SEGMENT = "replay segment"


class Replay(Protocol):
    """K ring buffers of rows (a single learner's buffer is one), as `layered.buffer` keeps them."""

    k: int
    capacity: int

    @property
    def stored(self) -> np.ndarray:
        """[K] rows stored in all."""

    def rows_since(self, since: np.ndarray) -> tuple[Any, np.ndarray]: ...

    def restore(self, stored: np.ndarray, segments: Iterable[tuple[Any, np.ndarray, np.ndarray]]) -> None: ...


class HasReplays(Protocol):
    """A learner (or a group's): its replay buffers by part, which checkpoints keep apart from its resume state."""

    @property
    def replays(self) -> Mapping[str, Replay]: ...


def replay_folder(checkpoint: Path) -> Path:
    """Where the segments of the replay buffers of the run (or group) checkpointed at `checkpoint` are."""
    return checkpoint.parent / "replay"


def replays_of(learners: Mapping[str, HasReplays]) -> dict[str, Replay]:
    """Every layer's replay buffers, by `<layer>.<part>`."""
    return {f"{name}.{part}": replay for name, learner in learners.items() for part, replay in learner.replays.items()}


class ReplayJournal:
    """The segments of a run's (or a group's) replay buffers in `folder`."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.files = Attachments(folder)
        self.manifests: dict[str, Manifest] = {}

    def record(self, replays: dict[str, Replay]) -> dict[str, Manifest]:
        """Write each buffer's rows stored since the last record as a new segment; the manifests that the
        checkpoint about to be written holds."""
        for key, replay in replays.items():
            manifest = self.manifests.get(key, {"stored": [0] * replay.k, "written": 0, "segments": []})
            rows, first = replay.rows_since(np.array(manifest["stored"], np.int64))
            counts = replay.stored - first
            oldest = replay.stored - replay.capacity  # the first row each seed's ring still holds
            segments = [s for s in manifest["segments"]
                        if np.any((np.array(s["counts"]) > 0) & (np.add(s["first"], s["counts"]) > oldest))]
            written = manifest["written"]
            if len(rows):
                file = f"{key}.{written:06d}.pt"
                segments.append({**self.files.write(file, SEGMENT, {"rows": rows, "first": first.tolist(),
                                                                    "counts": counts.tolist()}),
                                 "first": first.tolist(), "counts": counts.tolist()})
                written += 1
            self.manifests[key] = {"stored": replay.stored.tolist(), "written": written, "segments": segments}
        return dict(self.manifests)

    def prune(self) -> None:
        """Once a checkpoint with the latest manifests is written: remove the segments that neither it nor the
        one before it names."""
        self.files.prune(_files(self.manifests))

    def restore(self, manifests: dict[str, Manifest], replays: dict[str, Replay]) -> None:
        """Refill each buffer from the segments that a checkpoint's `manifests` name; the next record goes on
        from there."""
        self.manifests = dict(manifests)
        self.files.restore(_files(manifests))
        for key, replay in replays.items():
            manifest = self.manifests[key]
            replay.restore(np.array(manifest["stored"], np.int64), self._segments(manifest))

    def _segments(self, manifest: Manifest) -> Iterator[tuple[torch.Tensor, np.ndarray, np.ndarray]]:
        for segment in manifest["segments"]:
            saved = self.files.load(segment, SEGMENT)
            yield saved["rows"], np.array(saved["first"], np.int64), np.array(saved["counts"], np.int64)

    def clear(self) -> None:
        """Remove every segment (a group starting over, or one that has finished)."""
        self.files.clear()
        self.manifests = {}


def check_segments(folder: Path, manifests: dict[str, Manifest]) -> None:
    """Refuse (CheckpointError) the checkpoint whose `manifests` these are if a segment it names in `folder` is
    missing, damaged or not the one it was written with."""
    check_attachments(folder, [segment for manifest in manifests.values() for segment in manifest["segments"]],
                      SEGMENT)


def _files(manifests: dict[str, Manifest]) -> set[str]:
    return {segment["file"] for manifest in manifests.values() for segment in manifest["segments"]}
