"""A group's best weights beside its checkpoint: a seed's file is written when its phase's best evaluation
changes and only then, a checkpoint's files load back into the seeds' states, and files nothing names any
more are removed."""

from __future__ import annotations

import pytest
import torch

from layered.best_journal import BEST, BestJournal, check_best
from layered.checkpoint import CheckpointError, load_checkpoint
from layered.metrics import Evaluation
from layered.runstate import LoopState


def evaluated(state: LoopState, step: int, value: float) -> None:
    """An evaluation at `step` scoring `value`, as a loop books it: the weights kept where it is the best."""
    state.curve.append((step, Evaluation(value, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, {}, {}, {})))
    if state.best_index() == len(state.curve) - 1:
        state.best = {"layer": {"w": torch.full((2,), value)}}


def test_a_seeds_file_is_written_when_its_best_changes_and_only_then(tmp_path):
    states, journal = [LoopState(), LoopState()], BestJournal(tmp_path)
    assert journal.record([0, 3], states) == {"files": [None, None], "written": 0}, "nothing evaluated: no file"
    evaluated(states[0], 0, 1.0)
    evaluated(states[1], 0, 5.0)
    first = journal.record([0, 3], states)
    assert [a["file"] for a in first["files"]] == ["seed0.000000.pt", "seed3.000001.pt"]
    evaluated(states[0], 100, 2.0)  # a new best in seed 0
    evaluated(states[1], 100, 4.0)  # not in seed 3
    second = journal.record([0, 3], states)
    assert second["files"][0]["file"] == "seed0.000002.pt" and second["files"][1] == first["files"][1]
    assert second["written"] == 3
    assert load_checkpoint(tmp_path / "seed0.000002.pt", BEST)["layer"]["w"].tolist() == [2.0, 2.0]
    assert journal.record([0, 3], states) == second, "no change: nothing written"
    states[1].start_phase(1, ("fast",), 100, 100)  # a new phase: no best until its first evaluation
    assert journal.record([0, 3], states)["files"][1] is None


def test_a_checkpoints_files_load_into_the_states_and_the_next_record_goes_on_from_them(tmp_path):
    states, journal = [LoopState(), LoopState()], BestJournal(tmp_path)
    evaluated(states[0], 0, 1.0)
    evaluated(states[1], 0, 5.0)
    saved = journal.record([0, 1], states)
    journal.prune()
    loaded = [LoopState.from_json(state.to_json()) for state in states]  # as a checkpoint holds them: no weights
    resumed = BestJournal(tmp_path)
    resumed.load(saved, loaded)
    assert [s.best["layer"]["w"][0].item() for s in loaded] == [1.0, 5.0]
    assert resumed.record([0, 1], loaded) == saved, "the files loaded are the ones the states hold"
    evaluated(loaded[1], 100, 6.0)
    assert resumed.record([0, 1], loaded)["files"][1]["file"] == "seed1.000002.pt", "numbered on, nothing overwritten"


def test_files_neither_the_newest_nor_the_previous_checkpoint_names_are_removed(tmp_path):
    state, journal = LoopState(), BestJournal(tmp_path)
    named = []
    for step in range(4):
        evaluated(state, 100 * step, float(step))
        named.append(journal.record([0], [state])["files"][0]["file"])
        (tmp_path / f"seed0.{10 + step:06d}.pt").write_bytes(b"left by a crash")
        journal.prune()
    assert sorted(p.name for p in tmp_path.iterdir()) == named[-2:]


def test_a_damaged_or_missing_file_refuses_its_checkpoint(tmp_path):
    state, journal = LoopState(), BestJournal(tmp_path)
    evaluated(state, 0, 1.0)
    saved = journal.record([0], [state])
    check_best(tmp_path, saved)
    path = tmp_path / saved["files"][0]["file"]
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(CheckpointError, match="damaged"):
        check_best(tmp_path, saved)
    path.unlink()
    with pytest.raises(CheckpointError, match="cannot be read"):
        check_best(tmp_path, saved)
