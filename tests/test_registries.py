"""Every entry of every registry, tested the moment it is registered: each learner, combiner,
training order and environment family saves, loads, resumes and repeats itself exactly."""

import io
import re

import numpy as np
import pytest
import torch
from conftest import assert_same_run, stack_recipe, train_until_stopped
from gymnasium.spaces import Box

from layered import load_recipe, make_aec_env
from layered.buffer import Transition
from layered.combiners import COMBINERS, Gate
from layered.envs import FAMILIES
from layered.learners import LEARNERS, Learner
from layered.orders import ORDERS
from layered.outputs import OutputLayout
from layered.replay_journal import ReplayJournal
from layered.runs import train
from layered.orders import phases_of

SMALL = ["learner.hidden=[16, 16]", "learner.batch_size=16", "train.warmup=20",
         "eval.episodes=1", "eval.fresh_episodes=2"]
LAYOUTS = [OutputLayout(2), OutputLayout(2, gate_dims=1, gate=Gate.encoding), OutputLayout(2, max_repeat=3)]


def make_learner(name: str, seed: int):
    """The learner `name` on the first output layout it accepts, with small networks where it has them."""
    cls = LEARNERS.get(name)
    layout = next(lay for lay in LAYOUTS if cls.unfit(lay) is None)
    low = [-1.0] * (layout.action_dims + layout.gate_dims) + ([1.0] if layout.repeats else [])
    high = [1.0] * (layout.action_dims + layout.gate_dims) + ([float(layout.max_repeat)] if layout.repeats else [])
    small = {"hidden": [16], "batch_size": 8} if "hidden" in cls.Config.model_fields else {}
    config = cls.Config.model_validate({"kind": name, **small})
    obs = Box(-1.0, 1.0, (3,), np.float32)
    learner = cls(obs, Box(np.array(low, np.float32), np.array(high, np.float32)), layout, config, seed)
    rng = np.random.default_rng(0)
    for _ in range(32):
        o = rng.uniform(-1, 1, 3).astype(np.float32)
        path = ((o, 0.5, 1),) if layout.repeats else ()
        learner.observe(Transition(o, learner.random_action(), float(rng.normal()), o, False, 0.99, path))
    return learner


def behaviour(learner, updates: int = 3):
    """Update statistics, then greedy and exploring actions on fixed observations."""
    stats = [learner.update() for _ in range(updates)]
    obs = [np.full(3, x, np.float32) for x in (-0.5, 0.0, 0.5)]
    return stats, [learner.act(o, False).tolist() for o in obs], [learner.act(o, True).tolist() for o in obs]


@pytest.mark.parametrize("name", LEARNERS.names())
def test_learner_same_seed_same_updates_and_actions(name):
    assert behaviour(make_learner(name, 1)) == behaviour(make_learner(name, 1))


@pytest.mark.parametrize("name", LEARNERS.names())
def test_learner_save_load_gives_identical_actions(name):
    a, b = make_learner(name, 1), make_learner(name, 2)
    behaviour(a)
    b.load_state_dict(through_a_file(a.state_dict()))
    obs = np.full(3, 0.3, np.float32)
    assert np.array_equal(a.act(obs, False), b.act(obs, False))


@pytest.mark.parametrize("name", LEARNERS.names())
def test_learner_policy_module_acts_as_act(name):
    """What `layered export` writes is what the learner does at evaluation."""
    learner = make_learner(name, 1)
    if type(learner).policy is Learner.policy:  # (a plugin's may have none: `layered export` then refuses its layer)
        pytest.skip(f"the {name!r} learner has no exportable policy")
    behaviour(learner)
    policy = learner.policy()
    for x in np.linspace(-1, 1, 9):
        obs = np.array([x, -x, 0.5 * x], np.float32)
        assert np.array_equal(policy(torch.from_numpy(obs)).detach().numpy(), learner.act(obs, False))


@pytest.mark.parametrize("name", LEARNERS.names())
def test_learner_greedy_batch_is_its_greedy_act_row_by_row(name):
    """An evaluation's episodes played side by side get, row by row, what `act` without exploration gives."""
    learner = make_learner(name, 1)
    behaviour(learner)
    obs = np.random.default_rng(3).uniform(-1, 1, (7, 3)).astype(np.float32)
    batch = learner.greedy(obs)
    rows = np.stack([learner.act(o, False) for o in obs])
    assert batch.shape == rows.shape and batch.dtype == np.float32
    assert np.allclose(batch, rows, atol=1e-6)
    if type(learner).__module__.startswith("layered."):  # (a plugin's may act alike everywhere, as centre.py does)
        assert len({tuple(row) for row in rows.round(4)}) > 1  # (distinct observations give distinct outputs)


def through_a_file(state):
    """`state` as a checkpoint gives it back: written and read again, sharing no tensor."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


@pytest.mark.parametrize("name", LEARNERS.names())
def test_learner_resume_gives_an_identical_future(name, tmp_path):
    """What a run's checkpoint keeps of a learner, its resume state and its replay buffers' segments, is all
    its future depends on."""
    a, b = make_learner(name, 1), make_learner(name, 2)
    behaviour(a)
    manifests = ReplayJournal(tmp_path).record(dict(a.replays))
    b.load_resume_state(through_a_file(a.resume_state()))
    ReplayJournal(tmp_path).restore(manifests, dict(b.replays))
    assert behaviour(a) == behaviour(b)


def stopped_and_resumed_equals_whole(recipe, tmp_path, monkeypatch, steps: int, stop_after: int) -> None:
    """Stopped at the `stop_after`-th episode end and resumed, a run equals one that never stopped."""
    train(recipe, tmp_path / "whole", max_steps=steps, progress=False, label="x")
    train_until_stopped(monkeypatch, recipe, tmp_path / "run", stop_after, max_steps=steps, progress=False, label="x")
    train(recipe, tmp_path / "run", max_steps=steps, progress=False, label="x", resume=True)
    assert_same_run(tmp_path / "whole", tmp_path / "run")


@pytest.mark.parametrize("kind", COMBINERS.names())
def test_combiner_stack_resumes_exactly(kind, tmp_path, monkeypatch):
    recipe = load_recipe(stack_recipe([4, 1], kind).model_dump(), [*SMALL, "eval.every=200"])
    stopped_and_resumed_equals_whole(recipe, tmp_path, monkeypatch, steps=600, stop_after=4)


@pytest.mark.parametrize("order", ORDERS.names())
def test_order_resumes_exactly(order, tmp_path, monkeypatch):
    data = stack_recipe([4, 2, 1], ["gate", "residual-clip", "residual-clip"]).model_dump()
    data["train"] = {"order": order}
    if order == "explicit":
        data["train"]["phases"] = [{"learn": ["l2"]}, {"learn": ["l0", "l1"]}]
    recipe = load_recipe(data, [*SMALL, "eval.every=200"])
    episodes = len(phases_of(recipe)) * 400 // 200  # Pendulum's episodes are 200 steps
    stopped_and_resumed_equals_whole(recipe, tmp_path, monkeypatch, steps=400, stop_after=episodes // 2 + 1)


@pytest.mark.parametrize("family", FAMILIES.names())
def test_env_family_same_seed_same_trajectory_and_exact_resume(family, tmp_path, monkeypatch):
    env_id = FAMILIES.get(family).example

    def rollout(seed: int, max_iter: int = 120) -> list[list[float]]:
        env = make_aec_env(stack_recipe([2, 1], env=env_id), seed=seed)
        seen = []
        for name in env.agent_iter(max_iter=max_iter):
            obs, _, term, trunc, _ = env.last()
            seen.append(obs.tolist())
            env.step(None if term or trunc else np.full(env.action_space(name).shape, 0.3, np.float32))
        env.close()
        return seen

    assert rollout(3) == rollout(3) and rollout(3) != rollout(4)
    length = len(rollout(0, max_iter=10**6)) * 2 // 3  # the fast layer decides every step, the slow every other
    recipe = load_recipe(stack_recipe([2, 1], env=env_id).model_dump(),
                         [*SMALL, f"eval.every={length}", "eval.fresh_episodes=1"])
    stopped_and_resumed_equals_whole(recipe, tmp_path, monkeypatch, steps=length + 50, stop_after=1)


# --- entries that cannot work are refused when registered ----------------------------------------------------------


def _bad_entries():
    """Per registry, entries that cannot work and the words of their refusal."""
    from layered.envs import EnvFamily
    from layered.combiners import ResidualClip

    class NoRoute(COMBINERS.base):  # its abstract method left out
        pass

    class NarrowAdmit(ResidualClip):
        def admit(self, contribution):
            return contribution

    bare = type("Bare", (LEARNERS.base,), {name: (lambda self, *a: None) for name in
                                          ("act", "act_macs", "observe", "update", "state_dict", "load_state_dict")})

    class NoInfo(EnvFamily):
        example = "x:y"

        def make(self, name, render_mode=None):
            return None

    class NarrowMake(FAMILIES.get("gym")):
        def make(self, name):
            return None

    return [
        (COMBINERS, "x-object", object, TypeError, "not a subclass of Combiner"),
        (COMBINERS, "x-no-route", NoRoute, TypeError, "does not define route"),
        (COMBINERS, "x-narrow", NarrowAdmit, TypeError, "its admit(self, contribution) does not take"),
        (COMBINERS, "", ResidualClip, ValueError, "a name is letters"),
        (LEARNERS, "x-bare", bare, TypeError, "does not set Config"),
        (ORDERS, "x-one", lambda names: [], TypeError, "called with 2 positional arguments"),
        (ORDERS, "x-number", 42, TypeError, "not callable"),
        (FAMILIES, "x-no-info", NoInfo, TypeError, "does not define info"),
        (FAMILIES, "x-narrow", NarrowMake, TypeError, "its make(self, name) does not take"),
        (FAMILIES, "a:b", NoInfo, ValueError, "a name is letters"),
    ]


@pytest.mark.parametrize("case", range(10))
def test_an_entry_that_cannot_work_is_refused_when_registered_and_leaves_the_registry_as_it_was(case):
    registry, name, entry, error, words = _bad_entries()[case]
    before = registry.names()
    with pytest.raises(error, match=re.escape(words)):
        registry.register(name)(entry)
    assert registry.names() == before
