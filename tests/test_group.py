"""Seeds trained as one group (`layered train --seeds`): each seed's transitions are those its own stack
gives, each seed writes an ordinary run directory, and a group run is deterministic."""

import csv
import json
import re
import statistics
from pathlib import Path

import numpy as np
import pytest

from conftest import play_through_agent_view

from layered.agents import make_aec_env
from layered.cli import main
from layered.evaluate import evaluate
from layered.group import Group, Seed, group_recipes, stack_learners
from layered.group_eval import open_stacks
from layered.interrupt import StopRequest
from layered.learner_set import build_learners, load_learners
from layered.logs import CsvLog
from layered.run_logs import RunLogs
from layered.best_journal import BestJournal
from layered.checkpoint_writer import CheckpointWriter
from layered.replay_journal import ReplayJournal
from layered.results import EPISODE_FIELDS, metrics_fields
from layered.trainer import FRESH_MEASURES
from layered.rundir import RunDirError
from layered.runs import resume
from layered.orders import phases_of

ROOT = Path(__file__).resolve().parent.parent
TINY = ["train.warmup=40", "eval.every=150", "eval.episodes=1", "eval.fresh_episodes=1"]


def tiny_group(recipe, seeds, tmp_path, overrides=()):
    recipes = group_recipes(ROOT / "recipes" / recipe, seeds, [*TINY, *overrides])
    singles = [build_learners(r) for r in recipes]
    seeds_ = [Seed(r, tmp_path / f"seed{r.train.seed}",
                   RunLogs(CsvLog(tmp_path / f"m{r.train.seed}.csv", metrics_fields(r)),
                           CsvLog(tmp_path / f"e{r.train.seed}.csv", EPISODE_FIELDS)))
              for r in recipes]
    for seed in seeds_:
        seed.logs.begin()
    group = Group(seeds_, stack_learners(recipes, singles), None, False, tmp_path, [""] * len(recipes), StopRequest(),
                  ReplayJournal(tmp_path / "replay"), BestJournal(tmp_path / "best"), CheckpointWriter())
    return group, recipes, singles


def stored(group, name, k):
    """Seed k's transitions of layer `name` in the order stored: obs, action, reward, next obs, not done, discount."""
    return group.learners[name].replay.seed_rows(k)


def run_first_phase_then_replay(group, recipes, steps=230):
    """Run the group's first phase for `steps` base steps with no budget to stop it, then yield, per seed, its
    index and its own agent-view environment, reset as the group reset it (closed after)."""
    phase = phases_of(recipes[0])[0]
    for seed in group.seeds:
        seed.state.start_phase(0, phase.learn, 10**9, 10**9)
    group.run_phase(phase, steps)
    for k, recipe_k in enumerate(recipes):
        env = make_aec_env(recipe_k, active=list(phase.active))
        env.reset(seed=recipe_k.train.seed)
        yield k, env
        env.close()


@pytest.mark.parametrize("recipe, overrides", [
    ("inverted-double-pendulum/tla-realtime.toml", ["train.order=joint"]),  # delays, early ends, 2 layers learn
    ("pendulum/tla-o.toml", ["train.order=joint", "train.warmup=400"]),  # a gate committing and deferring
    ("research/pendulum-gate-over-residual-3.toml", ["train.order=joint", "train.phases=[]"]),  # 3 layers
])
def test_each_seeds_transitions_are_those_its_own_stack_gives(recipe, overrides, tmp_path):
    """Every action of the phase is a warm-up draw, so the group's stored transitions can be replayed
    action by action through each seed's own agent view (the single loop's semantics): the same
    observations, rewards, discounts and ends, for every layer."""
    group, recipes, _ = tiny_group(recipe, [0, 3], tmp_path, [*overrides, "train.warmup=100000"])
    learn = phases_of(recipes[0])[0].learn
    for k, env in run_first_phase_then_replay(group, recipes):
        theirs = {name: stored(group, name, k) for name in learn}
        actions = {name: iter(theirs[name][1]) for name in learn}
        mine = play_through_agent_view(env, lambda name, actions=actions: next(actions[name], None))
        for name in learn:
            obs, action, reward, next_obs, not_done, discount = theirs[name]
            # the replay ends where the first layer runs out of actions: at most a slow period short
            assert len(mine[name]) >= len(obs) - 8 > 10, name
            for t, transition in enumerate(mine[name][: len(obs)]):
                assert np.allclose(transition.obs, obs[t], atol=1e-6), (name, t)
                assert np.allclose(transition.action, action[t]), (name, t)
                # (stored in float32: a slow layer's reward summed over its period, ~270, is exact to ~1.5e-5)
                assert transition.reward == pytest.approx(float(reward[t, 0]), rel=1e-6, abs=1e-5), (name, t)
                assert np.allclose(transition.next_obs, next_obs[t], atol=1e-6), (name, t)
                assert (1.0 - transition.terminated) == not_done[t, 0], (name, t)
                assert transition.discount == pytest.approx(float(discount[t, 0])), (name, t)


# episodes one after the other; two at a time; more lanes than episodes; a phase with a layer not yet present
@pytest.mark.parametrize("lanes, phase", [(1, -1), (2, -1), (4, -1), (2, 0)])
def test_a_group_evaluates_each_seed_as_its_own_stack_would(tmp_path, lanes, phase):
    group, recipes, singles = tiny_group("pendulum/tla-c.toml", [0, 1], tmp_path)
    phase = phases_of(recipes[0])[phase]
    evaluator = open_stacks(recipes[0], phase.active, 2 * lanes, evaluation=True)  # seed k's lane l: row k * lanes + l
    together = group._evaluations(evaluator, 3)  # (seeded train.seed + eval.seed_offset, 100)
    for k, recipe in enumerate(recipes):
        env = make_aec_env(recipe, active=list(phase.active), evaluation=True, keep_trace=True)
        alone = evaluate(env, singles[k], 3, recipe.train.seed + 100)
        assert together[k].return_mean == pytest.approx(alone.return_mean, rel=1e-5)
        assert together[k].repetition == alone.repetition and together[k].decided == alone.decided
        assert together[k].contribution == pytest.approx(alone.contribution) and together[k].jerk == pytest.approx(
            alone.jerk)
        env.close()


def test_an_evaluator_holds_as_many_lanes_per_seed_as_the_caps_allow(tmp_path, monkeypatch):
    group, recipes, _ = tiny_group("pendulum/tla-c.toml", [0, 1], tmp_path)
    phase = phases_of(recipes[0])[-1]
    # 10 per seed; no more than the episodes; no more than the rows in all allow; at least one
    for episodes, cap, rows in ((100, 320, 20), (3, 320, 6), (100, 7, 6), (100, 1, 2)):
        monkeypatch.setattr("layered.group_eval.EVAL_ROWS", cap)
        _, rules, envs = group._evaluator(phase, episodes)
        envs.close()
        assert rules.rows == rows, (episodes, cap)


def test_a_group_writes_each_seed_an_ordinary_run_directory_and_writes_it_again_the_same(tmp_path, capsys):
    recipe = str(ROOT / "recipes/pendulum/tla-c.toml")
    for out in ("a", "b"):
        assert main(["train", recipe, "--seeds", "2,5", "--steps", "300", "--out", str(tmp_path / out), *TINY]) == 0
        if out == "a":  # each progress line: the seeds' mean return and its spread over them, as the report's
            said = re.findall(r"eval return (\S+) ± ([-\d.]+)", capsys.readouterr().err)[-1]
            last = [float(list(csv.DictReader((tmp_path / f"a/seed{k}/metrics.csv").open()))[-1]["return_mean"])
                    for k in (2, 5)]
            assert said == (f"{statistics.mean(last):.1f}", f"{statistics.pstdev(last):.1f}")
    for seed in (2, 5):
        a, b = tmp_path / "a" / f"seed{seed}", tmp_path / "b" / f"seed{seed}"
        for name in ("metrics.csv", "episodes.csv", "results.json", "recipe.toml"):
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
        recipe_k = group_recipes(recipe, [seed], TINY)[0]
        load_learners(recipe_k, a)  # an ordinary checkpoint of every layer
    assert (tmp_path / "a/seed2/metrics.csv").read_bytes() != (tmp_path / "a/seed5/metrics.csv").read_bytes()
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "a/seed5"), "--episodes", "1"]) == 0
    # the group evaluated again as a group: every measure its training wrote for its final weights, to the digit
    assert main(["eval", str(tmp_path / "a"), "--fresh", "--weights", "final"]) == 0
    for seed in (2, 5):
        final = json.loads((tmp_path / f"a/seed{seed}/results.json").read_text())["phases"][-1]
        again = json.loads((tmp_path / f"a/seed{seed}/eval/weights-final/fresh/"
                            "threshold-recipe-episodes-1-group.json").read_text())
        assert {k: again[k] for k in FRESH_MEASURES} == {k: final[f"fresh_final_{k}"] for k in FRESH_MEASURES}
    printed = capsys.readouterr().out
    over = json.loads((tmp_path / "a/eval/weights-final/fresh/threshold-recipe-episodes-1-group.json").read_text())
    returns = [json.loads((tmp_path / f"a/seed{seed}/results.json").read_text())["phases"][-1][
        "fresh_final_return_mean"] for seed in (2, 5)]
    assert over["seeds"] == [2, 5] and over["returns"] == returns  # the line over the seeds, kept in the group's
    assert f"over the 2 seeds: return {statistics.fmean(returns):.1f} ± {statistics.pstdev(returns):.1f}" in printed
    assert "seed2 " in printed
    assert main(["eval", str(tmp_path / "a"), "--video"]) == 2
    assert "--video: of one run" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "a"), "--out", str(tmp_path / "report")]) == 0
    assert "pendulum/tla-c" in capsys.readouterr().out
    with pytest.raises(RunDirError, match="group of seeds"):
        resume(tmp_path / "a/seed2")


def test_what_a_group_cannot_train_is_refused_before_anything_is_written(tmp_path, capsys):
    out = tmp_path / "g"
    assert main(["train", str(ROOT / "docs/examples/pendulum-centre.toml"), "--plugin",
                 str(ROOT / "docs/examples/centre.py"), "--seeds", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'centre' learner" in err[0] and "layered sweep` without --vectorize" in err[0]
    assert err[0].startswith(f"layered: error: {ROOT / 'docs/examples/pendulum-centre.toml'}: layers[0].learner.kind")
    assert not out.exists()
    assert main(["sweep", str(ROOT / "docs/examples/pendulum-centre.toml"), "--plugin",
                 str(ROOT / "docs/examples/centre.py"), "--seeds", "2", "--vectorize", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("layered: error: examples/pendulum-centre (--vectorize): layers[0]")
    assert not out.exists()
    assert main(["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", "2", "--out", str(out),
                 "learner.compile=inductor", "learner.actor_anchor=0.1"]) == 2
    err = capsys.readouterr().err
    assert "learner.compile" in err and "'cudagraphs'" in err and "learner.actor_anchor" in err
    assert not out.exists()
    for bad in ("3-1", "1,1", "x"):
        with pytest.raises(SystemExit) as stop:
            main(["train", str(ROOT / "recipes/pendulum/td3.toml"), "--seeds", bad, "--out", str(out)])
        assert stop.value.code == 2 and f"got {bad!r}" in capsys.readouterr().err
    assert not out.exists()


def test_a_repeating_layers_decisions_carry_the_path_its_own_stack_gives(tmp_path):
    """TempoRL's decisions as the group hands them to its learner (each with its path: per period of the
    repeat, what the layer saw, the period's reward and its discount units), replayed decision by decision
    through each seed's own agent view: the same transitions, paths included."""
    group, recipes, _ = tiny_group("pendulum/temporl.toml", [0, 3], tmp_path,
                                   ["train.warmup=100000", "layers.fast.period=3", "train.discount=step"])
    phase = phases_of(recipes[0])[0]
    name = phase.learn[0]
    decisions: list[list] = [[], []]
    learner = group.learners[name]
    observe = learner.observe

    def record(obs, output, reward, next_obs, terminated, discount, rows=None, paths=None):
        for k in np.flatnonzero(rows):
            decisions[k].append((obs[k].copy(), output[k].copy(), float(reward[k]), next_obs[k].copy(),
                                 bool(terminated[k]), float(discount[k]), [tuple(p) for p in paths[k]]))
        observe(obs, output, reward, next_obs, terminated, discount, rows, paths)

    learner.observe = record
    for k, env in run_first_phase_then_replay(group, recipes):
        outputs = iter([d[1] for d in decisions[k]])
        mine = play_through_agent_view(env, lambda _, outputs=outputs: next(outputs, None))[name]
        assert len(mine) == len(decisions[k]) > 20 and any(len(d[6]) > 1 for d in decisions[k])
        for t, (theirs, alone) in enumerate(zip(decisions[k], mine, strict=True)):
            obs, output, reward, next_obs, terminated, discount, path = theirs
            assert np.allclose(alone.obs, obs, atol=1e-6) and np.array_equal(alone.action, output), t
            assert alone.reward == pytest.approx(reward, abs=1e-5) and alone.terminated == terminated, t
            assert np.allclose(alone.next_obs, next_obs, atol=1e-6) and alone.discount == pytest.approx(discount), t
            assert len(alone.path) == len(path), t
            for (o1, r1, u1), (o2, r2, u2) in zip(alone.path, path, strict=True):
                assert np.allclose(o1, o2, atol=1e-6) and r1 == pytest.approx(r2, abs=1e-5) and u1 == u2, t


def test_a_steps_transitions_are_stored_while_the_environments_step_and_before_the_update(tmp_path, monkeypatch):
    """The transitions a step's decisions complete are stored after the environments are asked to step (the host's
    store runs beside their step, where it waits anyway) and before the update that samples them."""
    from layered.env_group import EnvGroup

    group, recipes, _ = tiny_group("pendulum/td3.toml", [0, 1], tmp_path)
    events = []

    def recorded(name, call):
        def record(*args, **kwargs):
            events.append(name)
            return call(*args, **kwargs)
        return record

    monkeypatch.setattr(EnvGroup, "step_async", recorded("step", EnvGroup.step_async))  # (bound as a method)
    learner = group.learners["fast"]
    monkeypatch.setattr(learner, "observe", recorded("store", learner.observe))
    monkeypatch.setattr(learner, "update", recorded("update", learner.update))
    phase = phases_of(recipes[0])[0]
    for seed in group.seeds:
        seed.state.start_phase(0, phase.learn, 10**9, 10**9)
    group.run_phase(phase, 60)  # (Pendulum's episodes last 200 steps: no episode ends, whose stores follow the step)
    assert events.count("store") == 59 and events.count("update") == 20  # (decisions 41 to 60: past the warm-up)
    assert all(events[t - 1] == "step" for t, event in enumerate(events) if event == "store")
    assert all(events[t - 1] == "store" for t, event in enumerate(events) if event == "update")


def test_each_seed_reads_back_the_losses_of_the_updates_it_took_part_in():
    """Three updates of three seeds: the losses each seed's loop state gets, written out by hand; a non-finite
    value of a seed left out of an update is never read, one of a seed that took part stops the group."""
    from types import SimpleNamespace

    import torch

    from layered.group import _read_back
    from layered.pending_losses import PendingLosses
    from layered.runstate import LoopState
    from layered.errors import Diverged

    def read(updates):
        pending, seeds = PendingLosses(), [SimpleNamespace(state=LoopState(losses={"fast": []})) for _ in range(3)]
        for values, took in updates:
            pending.add({n: torch.tensor(v, dtype=torch.float32) for n, v in values.items()},
                        {n: np.array(t) for n, t in took.items()})
        _read_back({"fast": pending}, {"fast": ("critic", "actor")}, seeds, 7)
        return [seed.state.losses["fast"] for seed in seeds]

    nan = float("nan")
    updates = [({"critic": [1.0, 2.0, nan]}, {"critic": [True, True, False]}),  # seed 2 left out: its value unread
               ({"critic": [3.0, nan, 4.0], "actor": [-1.0, nan, -2.0]},
                {"critic": [True, False, True], "actor": [True, False, False]}),  # seed 2's actor did not step
               ({"critic": [5.0, 6.0, 7.0], "actor": [-3.0, -4.0, -5.0]},
                {"critic": [True, True, True], "actor": [True, True, True]})]
    assert read(updates) == [
        [{"critic_loss": 1.0, "actor_loss": None}, {"critic_loss": 3.0, "actor_loss": -1.0},
         {"critic_loss": 5.0, "actor_loss": -3.0}],
        [{"critic_loss": 2.0, "actor_loss": None}, {"critic_loss": 6.0, "actor_loss": -4.0}],
        [{"critic_loss": 4.0, "actor_loss": None}, {"critic_loss": 7.0, "actor_loss": -5.0}]]
    updates[2][0]["actor"][1] = float("inf")
    with pytest.raises(Diverged, match="layer 'fast' met a non-finite loss in phase 0 at step 7"):
        read(updates)


def test_each_seed_of_a_group_starts_from_its_own_weights_named_by_seed(tmp_path, capsys):
    """`{seed}` in a layer's `weights` is each seed's own number: a fast phase trained as one group over each
    seed's slow layer; a seed whose file is missing is refused, naming its path, before anything is written."""
    import torch

    from layered.checkpoint import load_checkpoint

    small = ["learner.hidden=[32, 32]", "learner.batch_size=32", *TINY]
    slow = tmp_path / "slow"
    assert main(["train", str(ROOT / "recipes/pendulum/tla-c.toml"), "--seeds", "0,1", "--steps", "300", *small,
                 "train.order=explicit", 'train.phases=[{learn=["slow"]}]', "--out", str(slow)]) == 0
    fast = ["train", str(ROOT / "recipes/pendulum/tla-c.toml"), "--steps", "300", *small, "train.order=explicit",
            'train.phases=[{learn=["fast"],active=["slow","fast"]}]',
            f"layers.slow.weights={slow}/seed{{seed}}/checkpoints/slow.best.pt"]
    assert main([*fast, "--seeds", "0,1", "--out", str(tmp_path / "fast")]) == 0
    kept = [load_checkpoint(tmp_path / "fast" / f"seed{s}" / "checkpoints" / "slow.best.pt", "slow")["actor"]
            for s in (0, 1)]
    sources = [load_checkpoint(slow / f"seed{s}" / "checkpoints" / "slow.best.pt", "slow")["actor"] for s in (0, 1)]
    for own, source, other in zip(kept, sources, reversed(sources), strict=True):
        assert all(torch.equal(own[k], source[k]) for k in source)
        assert not all(torch.equal(own[k], other[k]) for k in source)
    capsys.readouterr()
    assert main([*fast, "--seeds", "1,2", "--out", str(tmp_path / "missing")]) == 2
    assert f"layers[0].weights: {slow}/seed2/checkpoints/slow.best.pt" in capsys.readouterr().err
    assert not (tmp_path / "missing").exists()


def test_a_learner_stacks_in_a_group_only_where_its_registered_class_names_a_group_of_its_own(monkeypatch):
    """A plugin subclassing a shipped learner may change its update, which the shipped learner's group would not
    run: it trains per seed unless its class names a group of its own."""
    from layered.group import group_class
    from layered.learners import LEARNERS
    from layered.learners.choice_group import GateTD3Group, TempoRLGroup
    from layered.learners.td3_group import TD3Group

    assert [group_class(kind) for kind in ("td3", "temporl", "td3-gate")] == [TD3Group, TempoRLGroup, GateTD3Group]
    mine = type("MyTD3", (LEARNERS.get("td3"),), {})
    monkeypatch.setitem(LEARNERS._entries, "my-td3", mine)
    assert group_class("my-td3") is None
    monkeypatch.setattr(mine, "Group", TD3Group, raising=False)
    assert group_class("my-td3") is TD3Group
