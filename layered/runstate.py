"""A run's training state: the loop's position as one object, and the checkpoint that saves it
together with the learners, every random generator and the recipe it was made with.

Checkpoints are taken at episode boundaries: no transition is then half complete and no
simulator state needs saving, only the training environment's random generator.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from layered.checkpoint import CheckpointError, load_latest, save_checkpoint
from layered.replay_journal import ReplayJournal, check_segments, replays_of
from layered.learners import Learner
from layered.metrics import Evaluation, best_evaluation
from layered.pending_losses import PendingLosses
from layered.rundir import steps_option


UpdateStats = dict[str, float | None]
"""One update's losses read back to the host, as `<name>_loss` for each of the learner's loss names (None
where the update did not compute it): what the loop averages per evaluation and checkpoints."""


@dataclass
class LoopState:
    """Where training stands; what the loop reads besides the learners, and so what a checkpoint saves."""

    phase: int = 0
    """Index of the phase under way (phases are numbered from 0 everywhere)."""
    step: int = 0
    """Base environment steps taken in this phase."""
    episode: int = 0
    """Training episodes started in this phase (the first is seeded, later ones continue its generator)."""
    next_eval: int = 0
    """The step at which the next evaluation is due."""
    next_checkpoint: int = 0
    """The step after which the next episode boundary takes a checkpoint."""
    decisions: dict[str, int] = field(default_factory=dict)
    """Per learning layer: decisions taken in this phase (the first `train.warmup` act at random)."""
    curve: list[tuple[int, Evaluation]] = field(default_factory=list)
    """(step, evaluation) of this phase so far."""
    losses: dict[str, list[UpdateStats]] = field(default_factory=dict)
    """Per learning layer: the losses of each update since the last evaluation, read back."""
    pending: dict[str, PendingLosses] = field(default_factory=dict, repr=False)
    """Per learning layer: the losses of updates not yet read back from the learner's device (none
    at a checkpoint: they are read back first)."""
    rows: list[dict[str, Any]] = field(default_factory=list)
    """The results row of each finished phase, as in results.json."""
    env_rng: dict[str, Any] | None = None
    """The training environment's random state at the checkpoint (None before its first episode)."""
    log_sizes: dict[str, int] = field(default_factory=dict)
    """Bytes each CSV log held at the checkpoint; a resumed run cuts them back to these."""
    best: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """The learning layers' weights at this phase's best evaluation so far (tensors, checkpointed
    beside the JSON of the rest)."""

    def best_index(self) -> int:
        """Index in `curve` of this phase's best evaluation so far (the earliest, on ties)."""
        return best_evaluation([evaluation.return_mean for _, evaluation in self.curve])

    def start_phase(self, phase: int, learn: tuple[str, ...], eval_every: int, checkpoint_every: int) -> None:
        """Move to the start of phase `phase`, whose `learn` layers start with no decisions."""
        self.phase, self.step, self.episode, self.env_rng = phase, 0, 0, None
        self.next_eval, self.next_checkpoint = eval_every, checkpoint_every
        self.decisions = dict.fromkeys(learn, 0)
        self.losses = {name: [] for name in learn}
        self.pending = {name: PendingLosses() for name in learn}
        self.curve, self.best = [], {}

    def finish_phase(self, row: dict[str, Any]) -> None:
        """Record the finished phase's results; the next phase has not started."""
        self.rows.append(row)
        self.phase, self.step, self.episode = self.phase + 1, 0, 0
        self.decisions, self.losses, self.pending, self.curve, self.best = {}, {}, {}, [], {}

    def to_json(self) -> str:
        """The state as JSON text (floats round-trip exactly)."""
        data = asdict(replace(self, best={}, pending={}))  # the weights are saved as tensors, beside
        del data["best"], data["pending"]
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str) -> LoopState:
        """The state `to_json` wrote."""
        data = json.loads(text)
        data["curve"] = [(step, Evaluation(**evaluation)) for step, evaluation in data["curve"]]
        return cls(**data, pending={name: PendingLosses() for name in data["losses"]})


UNDIGESTED = {"env": ("wait",)}
"""Settings a recipe's digest leaves out: how a group's environment processes wait for each other changes no
number, and a run checkpointed before the setting existed resumes with it."""


def digested(resolved_recipe: dict[str, Any]) -> dict[str, Any]:
    """A resolved recipe without its `UNDIGESTED` settings: what a checkpoint must have been taken with."""
    kept = dict(resolved_recipe)
    for section, keys in UNDIGESTED.items():
        kept[section] = {key: value for key, value in kept[section].items() if key not in keys}
    return kept


def recipe_digest(resolved_recipe: dict[str, Any]) -> str:
    """A fingerprint of a resolved recipe (but its `UNDIGESTED` settings), stable across key order."""
    return hashlib.sha256(json.dumps(digested(resolved_recipe), sort_keys=True).encode()).hexdigest()


def recipe_differences(saved: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """`key: saved -> current` for every value that differs between two resolved recipes."""
    out = []
    for key in sorted(set(saved) | set(current), key=str):
        a, b, where = saved.get(key), current.get(key), f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += recipe_differences(a, b, f"{where}.")
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for k, (x, y) in enumerate(zip(a, b, strict=True)):
                out += recipe_differences({f"{where}[{k}]": x}, {f"{where}[{k}]": y})
        elif a != b:
            out.append(f"{where}: {a!r} -> {b!r}")
    return out


def save_state(path: Path, state: LoopState, learners: dict[str, Learner], resolved_recipe: dict[str, Any],
             max_steps: int | None, journal: ReplayJournal) -> None:
    """Checkpoint the whole training state at an episode boundary; the previous checkpoint is kept. The replay
    buffers' new rows go to `journal`'s segments, which the checkpoint names."""
    replays = journal.record(replays_of(learners))
    save_checkpoint(path, "run", {
        "recipe": json.dumps(resolved_recipe, sort_keys=True), "recipe_digest": recipe_digest(resolved_recipe),
        "max_steps": max_steps, "loop": state.to_json(), "best": state.best, "torch_rng": torch.get_rng_state(),
        "learners": {name: learner.resume_state() for name, learner in learners.items()}, "replays": replays,
    }, keep_previous=True)
    journal.prune()


def load_state(path: Path, learners: dict[str, Learner], resolved_recipe: dict[str, Any],
             max_steps: int | None, journal: ReplayJournal, changed_from: str | None = None) -> LoopState | None:
    """Restore the newest usable checkpoint into `learners` (their replay buffers from `journal`'s segments); its
    loop state, or None if there is none.

    Refuses, naming the difference, a checkpoint made with another recipe or another `--steps`; one
    made with the recipe whose digest is `changed_from` (the run's settings were changed since, and
    `learners` are built with the changed ones) is taken.
    """
    saved = load_latest(path, "run", lambda saved: check_segments(journal.folder, saved.get("replays", {})))
    if saved is None:
        return None
    if saved["recipe_digest"] not in (recipe_digest(resolved_recipe), changed_from):
        changes = recipe_differences(digested(json.loads(saved["recipe"])), digested(resolved_recipe))
        raise CheckpointError(f"{path.parent.parent}: the recipe differs from the one the run was started with "
                              f"({'; '.join(changes[:3])}{'; ...' if len(changes) > 3 else ''})")
    if saved["max_steps"] != max_steps:
        raise CheckpointError(f"{path.parent.parent}: the run was started with {steps_option(saved['max_steps'])}, "
                              f"not {steps_option(max_steps)}")
    for name, learner in learners.items():
        learner.load_resume_state(saved["learners"][name])
    if "replays" in saved:  # (a checkpoint of layered 0.1.0 holds its buffers in the learners' states)
        journal.restore(saved["replays"], replays_of(learners))
    torch.set_rng_state(saved["torch_rng"])
    state = LoopState.from_json(saved["loop"])
    state.best = saved["best"]
    return state
