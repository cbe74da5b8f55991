"""Checkpoints: tensors plus a format version, written atomically, verified by a checksum, loaded
weights-only.

A checkpoint file is one header line, `LAYERED-CHECKPOINT <format> <sha256 of the rest>`, then what
torch.save wrote; a file damaged anywhere, header included, fails the check and is refused by name.
A run's training state keeps its previous checkpoint beside the newest, so a damaged or unreadable
one costs one checkpoint interval, not the run. Files of format 2 (no header, no checksum) still load.
"""

from __future__ import annotations

import copy
import hashlib
import io
import os
import pickle
import re
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import torch

from layered.errors import BadInput

FORMAT_VERSION = 3
MAGIC = b"LAYERED-CHECKPOINT"


class CheckpointError(BadInput, RuntimeError):
    """A checkpoint that is missing, corrupted or of another format version."""


def previous(path: Path) -> Path:
    """Where the checkpoint before `path`'s newest one is kept."""
    return path.with_name(f"{path.stem}.prev{path.suffix}")


def _write_atomically(path: Path, write: Callable[[BinaryIO], object], keep_previous: bool = False) -> None:
    """Write `path` through a temporary file flushed to disk and renamed into place, so that the file
    is wholly the old or wholly the new content; with `keep_previous` the old one becomes `previous(path)`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if keep_previous and path.exists():
            os.replace(path, previous(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def unfinished_write(name: str) -> str | None:
    """The name of the file whose write was cut short, where `name` is a temporary file `_write_atomically` left
    behind (`.NAME.` and mkstemp's 8 characters); None for any other name."""
    match = re.fullmatch(r"\.(.+)\.[a-z0-9_]{8}", name)
    return match.group(1) if match else None


def write_atomically(path: Path, text: str) -> None:
    """Write a text file so that it is either wholly the old or wholly the new content."""
    _write_atomically(path, lambda f: f.write(text.encode("utf-8")))


def save_checkpoint(path: Path, layer: str, state: dict[str, Any], keep_previous: bool = False) -> str:
    """Write `state` (of `layer`, or `run`) to `path`; a crash mid-write leaves the old file intact. The
    checksum of what was written (see `verified_digest`).

    With `keep_previous` the file it replaces is kept as `previous(path)`.
    """
    body = io.BytesIO()
    torch.save(canonical({"format_version": FORMAT_VERSION, "layer": layer, "state": state}), body)
    digest = hashlib.sha256(body.getbuffer()).hexdigest()
    header = b"%s %d %s\n" % (MAGIC, FORMAT_VERSION, digest.encode())

    def write(f: BinaryIO) -> None:
        f.write(header)
        f.write(body.getbuffer())  # (not joined to the header: that would copy the whole body once more)

    _write_atomically(path, write, keep_previous)
    return digest


def canonical(value: Any, seen: dict[int, Any] | None = None) -> Any:
    """`value` with every string interned, its dicts, lists and tuples rebuilt around them (a dict's attributes too,
    as a state_dict's `_metadata`; what is shared stays shared): pickle writes a string met before as a reference by
    the object's identity, so equal states were written in other bytes where one had been read back from a file (a
    resumed group's best weights) and the other built in memory."""
    if isinstance(value, str):
        return sys.intern(value)
    if not isinstance(value, dict | list | tuple):
        return value
    seen = {} if seen is None else seen
    if id(value) in seen:
        return seen[id(value)]
    rebuilt: Any
    if isinstance(value, dict):
        rebuilt = copy.copy(value)  # (keeps a subclass's own state, as a defaultdict's factory)
        rebuilt.clear()
        seen[id(value)] = rebuilt
        rebuilt.update((canonical(k, seen), canonical(v, seen)) for k, v in value.items())
        for name, attribute in getattr(value, "__dict__", {}).items():
            setattr(rebuilt, name, canonical(attribute, seen))
    elif type(value) in (list, tuple):
        rebuilt = type(value)(canonical(v, seen) for v in value)
    else:  # (a named tuple or a list of another kind: as it is)
        rebuilt = value
    seen[id(value)] = rebuilt
    return rebuilt


def verified_digest(path: Path) -> str:
    """The checksum in the header of the checkpoint at `path`, once its content has been checked against it."""
    content = _read(path)
    if _verified_body(path, content) is content:
        raise CheckpointError(f"{path}: written in checkpoint format 2, which has no checksum")
    return content.partition(b"\n")[0].split(b" ")[2].decode()


def load_checkpoint(path: Path, layer: str) -> dict[str, Any]:
    """The learner state saved for `layer` at `path`."""
    if not path.exists():
        raise CheckpointError(f"{path}: no checkpoint for layer {layer!r}")
    body = _verified_body(path, _read(path))
    try:  # learners move what they load to their device
        data = torch.load(io.BytesIO(body), weights_only=True, map_location="cpu")
    except (RuntimeError, EOFError, pickle.UnpicklingError, ValueError, OSError) as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({e.__class__.__name__}: {e})") from None
    if not isinstance(data, dict) or data.get("layer") != layer:
        raise CheckpointError(f"{path}: not a checkpoint of {layer!r}")
    if data.get("format_version") not in (2, FORMAT_VERSION):
        raise CheckpointError(f"{path}: written in checkpoint format {data.get('format_version')}, this layered "
                              f"reads format {FORMAT_VERSION}")
    return data["state"]


def _read(path: Path) -> bytes:
    """The bytes of the file at `path`; one that cannot be read is a CheckpointError."""
    try:
        return path.read_bytes()
    except OSError as e:
        raise CheckpointError(f"{path}: cannot be read ({e.strerror or e})") from None


def _verified_body(path: Path, content: bytes) -> bytes:
    """What torch.save wrote, after checking the header's checksum (a format-2 file has neither)."""
    if content.startswith(b"PK"):  # format 2: a bare zip archive
        return content
    header, newline, body = content.partition(b"\n")
    parts = header.split(b" ")
    if not newline or len(parts) != 3 or parts[0] != MAGIC:
        raise CheckpointError(f"{path}: not a checkpoint (damaged or of another program)")
    if hashlib.sha256(body).hexdigest().encode() != parts[2]:
        raise CheckpointError(f"{path}: damaged (its checksum does not match its content)")
    return body


def load_latest(path: Path, layer: str, check: Callable[[dict[str, Any]], None] | None = None,
                tidy: bool = True) -> dict[str, Any] | None:
    """The newest readable state of `path` or, failing that, of `previous(path)`; None if neither
    exists. With `tidy` (the run's writer, resuming), unfinished temporary files of an interrupted write are
    removed; a reader beside a writer at work leaves them. A state that `check` refuses (raising
    CheckpointError: what it names elsewhere is missing or damaged) counts as unreadable."""
    for stale in path.parent.glob(f".{path.name}.*") if tidy else ():
        stale.unlink(missing_ok=True)
    problems = []
    for candidate in (path, previous(path)):
        if not candidate.exists():
            continue
        try:
            state = load_checkpoint(candidate, layer)
            if check is not None:
                check(state)
        except CheckpointError as e:
            problems.append(str(e))
            continue
        if problems:
            print(f"layered: warning: {problems[0]}; using the previous checkpoint {candidate.name}", file=sys.stderr)
        return state
    if problems:
        raise CheckpointError("; ".join(dict.fromkeys(problems)) + "; no usable checkpoint is left")  # (a file both
        # checkpoints name, such as a replay segment, once)
    return None
