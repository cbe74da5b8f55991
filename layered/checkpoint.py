"""Checkpoints of layers: tensors plus a format version, written atomically, loaded weights-only."""

from __future__ import annotations

import os
import pickle
import tempfile
from pathlib import Path
from typing import Any

import torch

FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, corrupted or of another format version."""


def save_checkpoint(path: Path, layer: str, state: dict[str, Any]) -> None:
    """Write one layer's learner state to `path`; a crash mid-write leaves any old file intact."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format_version": FORMAT_VERSION, "layer": layer, "state": state}, f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path, layer: str) -> dict[str, Any]:
    """The learner state saved for `layer` at `path`."""
    if not path.exists():
        raise CheckpointError(f"{path}: no checkpoint for layer {layer!r}")
    try:
        data = torch.load(path, weights_only=True)
    except (RuntimeError, EOFError, pickle.UnpicklingError, ValueError) as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({e.__class__.__name__}: {e})") from None
    if not isinstance(data, dict) or data.get("format_version") != FORMAT_VERSION or data.get("layer") != layer:
        raise CheckpointError(f"{path}: not a format-{FORMAT_VERSION} checkpoint of layer {layer!r}")
    return data["state"]
