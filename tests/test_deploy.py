"""`layered deploy`: the layers of a stack as processes of their own. In lockstep they execute the actions
of `layered eval`; against the clock, late answers take effect late by the rules; dead, stalled or
foreign processes are noticed, reported in one line, and no process outlives the command."""

import json
import os
import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest

from layered import load_recipe
from layered.cli import main
from layered import layer_process
from layered.agents import make_aec_env
from layered.deploy import Decision, Driver, Episode, Settings
from layered.deploy_measures import largest_difference, layer_measures, run_measures
from layered.deploy_run import deploy, start_layers
from layered.envs import make_env
from layered.evaluate import evaluate, run_episode
from layered.combiners import Gate, ResidualClip
from layered.layer_process import Fault, LayerFault, LayerProcess, Link, Reply, Request
from layered.learner_set import build_learners
from layered.rules import Layer, Rules
from layered.run_evals import TrainedRun
from layered.orders import phases_of

from test_export import STACKS, SMALL


def untrained(path, overrides, tmp_path):
    """A run of untrained learners: the rules and the processes, not the policies, are under test."""
    recipe = load_recipe(path, SMALL + overrides)
    return TrainedRun(tmp_path, recipe, build_learners(recipe), list(phases_of(recipe)[-1].active))


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


# --- the rules of a late answer -------------------------------------------------------------------------


def one_layer(**kwargs):
    low, high = np.array([-1.0], np.float32), np.array([1.0], np.float32)
    size = 2 if kwargs.get("max_repeat", 1) > 1 else 1
    layer = Layer("a", kwargs.pop("period", 1), np.array([-1.0, 1.0][:size], np.float32) if size == 2 else low,
                  np.array([1.0, 3.0][:size], np.float32) if size == 2 else high, **kwargs)
    return Rules([layer], [0], low, high)


def test_a_late_answer_in_flight_lands_as_decided_then_late_then_is_stale():
    rules = one_layer(delay=1)
    rules.decide(0, np.array([[0.5]]))  # step 0: a placeholder goes in flight, the zero output lands
    assert rules.amend(0, 0, np.array([[0.7]])) == "in flight"
    assert rules.held[0][0, 0] == 0.0
    rules.tick()
    rules.decide(0, np.array([[0.1]]))  # step 1: the amended 0.7 lands
    assert rules.held[0][0, 0] == pytest.approx(0.7)
    assert rules.amend(0, 1, np.array([[0.9]])) == "late"  # the decision that landed, answered only now
    assert rules.held[0][0, 0] == pytest.approx(0.9)
    assert rules.inflight[0][0, 0, 0] == pytest.approx(0.1)
    assert rules.amend(0, 2, np.array([[-0.9]])) == "stale"
    assert rules.held[0][0, 0] == pytest.approx(0.9)


def test_a_late_answer_without_delay_is_held_at_once_and_clipped_and_resets_its_repeat():
    rules = one_layer(max_repeat=3)
    rules.decide(0, np.array([[0.2, 1.0]]))  # a placeholder repeating once: decides again at step 1
    assert rules.resume_at[0][0] == 1
    assert rules.amend(0, 0, np.array([[5.0, 3.0]])) == "late"
    assert rules.held[0][0].tolist() == [1.0, 3.0]  # clipped to the layer's bounds
    assert rules.resume_at[0][0] == 3  # the answer repeats three periods
    assert rules.amend(0, 1, np.array([[0.0, 1.0]])) == "stale"


# --- measures, by hand ----------------------------------------------------------------------------------


def test_layer_measures_count_misses_late_dropped_and_the_delays_seen():
    decisions = [
        Decision(0, step=0, sent=0.0, deadline=1.0, answered=0.001, compute_s=0.0005, landed=0),  # on time
        Decision(0, step=1, sent=1.0, deadline=2.0, answered=1.003, compute_s=0.0005, landed=3, missed=True),
        Decision(0, step=2, sent=2.0, deadline=3.0, missed=True),  # never answered in time to land: dropped
        Decision(0, step=3, sent=3.0, deadline=4.0),  # the episode ended with it in flight: not settled
    ]
    m = layer_measures(decisions, scheduled=0)
    assert (m["requests"], m["answered"], m["settled"], m["missed"], m["late"], m["dropped"]) == (4, 2, 3, 2, 1, 1)
    assert m["miss_rate"] == pytest.approx(2 / 3)
    assert m["latency_ms"]["median"] == pytest.approx(2.0)  # of 1 ms and 3 ms
    assert m["latency_ms"]["p99"] == pytest.approx(1 + 2 * 0.99)
    assert m["delay_seen"] == {"0": 1, "2": 1}
    assert m["mean_delay_seen"] == pytest.approx(1.0)


def test_run_measures_and_action_differences():
    episodes = [Episode(-10.0, np.zeros((4, 1)), 0.2), Episode(-20.0, np.zeros((6, 1)), 0.3)]
    m = run_measures(episodes, timestep=0.05)
    assert (m["return_mean"], m["return_std"], m["steps"]) == (-15.0, 5.0, 10)
    assert m["steps_per_s"] == pytest.approx(20.0)
    assert m["real_time_factor"] == pytest.approx(1.0)  # 10 steps of 0.05 s in 0.5 s
    assert largest_difference([np.array([[0.5], [1.0]])], [np.array([[0.25], [1.0]])]) == 0.25
    assert largest_difference([np.zeros((2, 1))], [np.zeros((3, 1))]) == float("inf")


@pytest.mark.parametrize(("text", "mean", "jitter"), [("5ms", 5e-3, 0.0), ("5ms±2ms", 5e-3, 2e-3),
                                                      ("0.1s+-500us", 0.1, 5e-4)])
def test_link_delays_parse(text, mean, jitter):
    link = Link.parse(text)
    assert (link.mean_s, link.jitter_s) == pytest.approx((mean, jitter))
    samples = [link.sample(np.random.default_rng(k)) for k in range(50)]
    assert min(samples) >= mean - jitter and max(samples) <= mean + jitter


@pytest.mark.parametrize("given", [["slow=2ms", "5ms"], ["5ms", "slow=2ms"]])
def test_a_layers_own_link_delay_takes_the_place_of_the_one_for_every_layer_in_either_order(given):
    from layered.cli import _per_layer

    links = _per_layer(given, "=", Link.parse, ["slow", "fast"], "--link-delay", bare_for_all=True)
    assert links == {"slow": Link(2e-3), "fast": Link(5e-3)}


@pytest.mark.parametrize("text", ["5", "5ms±6ms", "fast", "-1ms"])
def test_bad_link_delays_are_refused(text):
    with pytest.raises(ValueError, match="link delay"):
        Link.parse(text)


def test_faults_parse():
    assert Fault.parse("die@3") == Fault("die", 3)
    assert Fault.parse("stall@10") == Fault("stall", 10)
    with pytest.raises(ValueError, match="die@N or stall@N"):
        Fault.parse("hang@3")


# --- lockstep equals eval -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(STACKS))
def test_lockstep_executes_the_actions_of_layered_eval(name, tmp_path):
    run = untrained(*STACKS[name], tmp_path)
    [row] = deploy(run, [Settings(lockstep=True)], episodes=2, out=tmp_path / "deploy", notify=lambda _: None)
    assert row["steps"] >= 15  # untrained, the double pendulum falls within about 8 steps per episode
    assert row["max_action_difference"] == 0.0 and row["same_actions_as_eval"]
    assert row["returns"] == row["eval_returns"]
    env = make_aec_env(run.recipe, active=run.active, evaluation=True, keep_trace=True)
    assert row["return_mean"] == pytest.approx(evaluate(env, run.learners, 2, run.seed).return_mean, rel=1e-12)
    env.close()
    assert all(layer["missed"] == 0 and layer["requests"] == layer["answered"] for layer in row["layers"].values())
    delays = {name: layer["scheduled_delay"] for name, layer in row["layers"].items()}
    assert all(set(layer["delay_seen"]) <= {str(delays[name])} for name, layer in row["layers"].items())
    assert not any(_alive(pid) for pid in row["pids"])


def test_against_the_clock_every_decision_is_settled_and_seen_no_earlier_than_trained(tmp_path):
    run = untrained("inverted-double-pendulum/tla-realtime.toml", [], tmp_path)
    [row] = deploy(run, [Settings(speed=4.0)], episodes=2, out=tmp_path / "deploy", notify=lambda _: None)
    assert row["completed"] and row["real_time_factor"] == pytest.approx(4.0, rel=0.5)
    for layer in row["layers"].values():
        assert layer["settled"] >= layer["requests"] - 2 * 2  # at most one in flight per episode end and layer
        assert all(int(k) >= layer["scheduled_delay"] for k in layer["delay_seen"])
        assert layer["latency_ms"]["median"] < 1e3 * layer["period_s"]


class Scripted:
    """A layer's end answering with `value(step)`, available to the driver once its step counter reaches
    the decision's step plus `lag(step)`: a timeline to trace by hand, with no process and no timing noise."""

    def __init__(self, name, value, lag):
        self.name, self.pid, self.waitable, self.value, self.lag = name, None, None, value, lag
        self.driver, self.sent = None, []

    def wait_ready(self, timeout_s):
        pass

    def send(self, request):
        self.sent.append(request)

    def receive(self, timeout_s):
        if self.sent and self.driver.t >= self.sent[0].step + self.lag(self.sent[0].step):
            r = self.sent.pop(0)
            return Reply(layer_process.PROTOCOL, self.name, r.episode, r.step,
                         np.atleast_1d(np.float32(self.value(r.step))), 0.0, r.sent, r.sent)
        time.sleep(min(timeout_s, 0.001))
        return None

    def abandon(self):
        self.abandoned = True

    def close(self):
        self.closed = True


def play_scripted(layers, ends, steps, notify=lambda _: None):
    """One episode of `steps` base steps of Pendulum driven by `Scripted` ends at real time (base steps of 50 ms:
    long enough that the machine's own delays do not make an answer miss its step); the driver and the episode."""
    low, high = np.float32([-2.0]), np.float32([2.0])
    driver = Driver(Rules(layers, [0, 1], low, high), ends, timestep=0.05, settings=Settings(speed=1.0),
                    notify=notify)
    for end in ends.values():
        end.driver = driver
    env = gym.wrappers.TimeLimit(make_env("Pendulum-v1"), steps)
    episode = driver.play(env, 0)
    env.close()
    return driver, episode


def test_a_timeline_traced_by_hand_late_answers_of_a_delayed_slow_layer_take_effect_when_they_come():
    """Slow: period 2, delay 1, answers 0.1 x (step + 1), the one for step 2 three steps late. Fast:
    period 1, no delay, answers 0.01 x (step + 1) at once. Slow's contribution, step by step: 0 and 0
    (nothing landed), 0.1 and 0.1 (step 0's answer lands at step 2), 0.1 at step 4 (step 2's answer is
    due but missing: its place holds the newest output in flight, step 0's), 0.3 at step 5 (it came:
    late, it takes effect at once), 0.5 from step 6 (step 4's answer, on time) ..."""
    low, high = np.float32([-2.0]), np.float32([2.0])
    layers = [Layer("slow", 2, low, high, combiner=ResidualClip(), delay=1), Layer("fast", 1, low, high, sees=(0,))]
    ends = {0: Scripted("slow", lambda s: 0.1 * (s + 1), lambda s: 3 if s == 2 else 0),
            1: Scripted("fast", lambda s: 0.01 * (s + 1), lambda s: 0)}
    driver, episode = play_scripted(layers, ends, 10)
    slow = [0, 0, 0.1, 0.1, 0.1, 0.3, 0.5, 0.5, 0.7, 0.7]
    np.testing.assert_allclose(episode.actions[:, 0], [s + 0.01 * (t + 1) for t, s in enumerate(slow)], atol=1e-6)
    decisions = {(d.layer, d.step): d for d in driver.decisions}
    late = decisions[0, 2]
    assert late.missed and late.landed == 5 and late.landed - late.step == 3
    assert all(not d.missed for key, d in decisions.items() if key != (0, 2))
    m = layer_measures([d for d in driver.decisions if d.layer == 0], scheduled=2)
    assert m["delay_seen"] == {"2": 3, "3": 1} and (m["missed"], m["late"], m["dropped"]) == (1, 1, 0)


def test_a_faster_layer_asked_before_an_answer_it_sees_in_flight_came_is_counted_though_none_was_late():
    """Mid: period 2, delay 1, its step-0 answer coming at step 2, its deadline: on time. Fast: period 1, delay 1,
    seeing mid's outputs in flight beside its own: asked at step 1, its output lands at step 2 beside mid's step-0
    output, whose answer has not come; the simulated setting would have shown it. Counted, not missed."""
    low, high = np.float32([-2.0]), np.float32([2.0])
    layers = [Layer("mid", 2, low, high, combiner=ResidualClip(), delay=1),
              Layer("fast", 1, low, high, sees=(0,), delay=1, sees_in_flight=True)]
    ends = {0: Scripted("mid", lambda s: 0.1 * (s + 1), lambda s: 2 if s == 0 else 0),
            1: Scripted("fast", lambda s: 0.01, lambda s: 0)}
    driver, _ = play_scripted(layers, ends, 8)
    assert [d.step for d in driver.decisions if d.unseen] == [1] and driver.decisions[0].layer == 0
    mid = layer_measures([d for d in driver.decisions if d.layer == 0], scheduled=2)
    fast = layer_measures([d for d in driver.decisions if d.layer == 1], scheduled=1)
    assert (mid["missed"], mid["asked_unseen"], fast["missed"], fast["asked_unseen"]) == (0, 0, 0, 1)


def test_a_stalled_layer_is_abandoned_without_the_clock_waiting_for_its_process_to_end():
    """A fault under `hold` stops the layer's process at once (`abandon`), not waiting for it to exit (`close`, up to
    a second, which cost the healthy layers their deadlines); the deployment closes every end after its episodes."""
    low, high = np.float32([-2.0]), np.float32([2.0])
    layers = [Layer("slow", 2, low, high, combiner=ResidualClip()), Layer("fast", 1, low, high, sees=(0,))]
    ends = {0: Scripted("slow", lambda s: 0.1, lambda s: 0), 1: Scripted("fast", lambda s: 0.01,
                                                                           lambda s: 10**6 if s >= 3 else 0)}
    driver, _ = play_scripted(layers, ends, 10)
    assert 1 in driver.dead and getattr(ends[1], "abandoned", False) and not getattr(ends[1], "closed", False)
    assert not getattr(ends[0], "abandoned", False)


def test_a_stalled_gate_defers_to_the_layers_below_it_from_then_on():
    """A gate's last output held would keep its commit, and the layers below it out, for good: under `hold` a
    faulted gate defers instead. Slow: period 2, a gate committing to 0.5, silent from step 4 on; fast: 0.01."""
    low, high = np.float32([-2.0]), np.float32([2.0])
    layers = [Layer("slow", 2, np.float32([-2.0, -1.0]), np.float32([2.0, 1.0]), combiner=Gate()),
              Layer("fast", 1, low, high)]
    ends = {0: Scripted("slow", lambda s: [0.5, 1.0], lambda s: 10**6 if s >= 4 else 0),
            1: Scripted("fast", lambda s: 0.01, lambda s: 0)}
    said = []
    driver, episode = play_scripted(layers, ends, 12, said.append)
    assert 0 in driver.dead and any("going on with the layers below it, its gate deferring" in line for line in said)
    np.testing.assert_allclose(episode.actions[:4, 0], 0.5)  # committed: fast not asked
    assert episode.actions[-1, 0] == pytest.approx(0.01)  # the gate deferring: fast acts
    assert {d.step for d in driver.decisions if d.layer == 1} >= {10, 11}


def test_a_link_slower_than_a_step_delays_answers_without_queueing_them(tmp_path):
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    # steps of 5 ms, a round trip of 10 ms: every fast answer misses its step, and none waits for the one before.
    # Late answers keep coming every step, so the layer is slow, not stalled: a stall is a silence of 20 ms past
    # a deadline, four steps, which leaves room for a loaded machine
    [row] = deploy(run, [Settings(speed=10.0, links={"fast": Link(5e-3)})], episodes=1, out=tmp_path / "deploy",
                   notify=lambda _: None)
    fast = row["layers"]["fast"]
    assert not row["faults"] and row["steps"] == 200
    # (answers queued behind each other would come later and later: hundreds of ms within the episode)
    assert 10 <= fast["latency_ms"]["median"] < 25 and fast["latency_ms"]["p99"] < 50
    # (the slow layer, with no link, answers in time but where the machine is busy: 14% late beside a training run)
    assert fast["miss_rate"] > 0.9 and row["layers"]["slow"]["miss_rate"] < 0.5


# --- faults ---------------------------------------------------------------------------------------------


def test_a_layer_that_dies_is_reported_and_the_stack_goes_on_without_it(tmp_path):
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    lines = []
    [row] = deploy(run, [Settings(lockstep=True, faults={"fast": Fault("die", 30)})], episodes=2,
                   out=tmp_path / "deploy", notify=lines.append)
    assert len(lines) == 3 and "layer 'fast'" in lines[0] and "died" in lines[0] and "going on" in lines[0]
    assert lines[1].startswith("lockstep: episode 1 of 2: return ")  # (progress; the last episode's is the row's)
    assert row["episodes"] == 2 and len(row["faults"]) == 1 and not row["completed"]
    assert row["layers"]["fast"]["requests"] == 30
    assert not any(_alive(pid) for pid in row["pids"])


def test_without_its_fast_layer_the_stack_acts_as_its_slow_layer_alone(tmp_path):
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    from layered.export import export_stack

    directory = export_stack(run.recipe, run.learners, run.active, tmp_path / "export", "torchscript")
    rules = Rules.from_json(json.loads((directory / "stack.json").read_text())["rules"])
    ends = start_layers(rules, directory, Settings(lockstep=True, faults={"fast": Fault("die", 5)}), 0)
    driver = Driver(rules, ends, 0.05, Settings(lockstep=True), notify=lambda _: None)
    env = make_env("Pendulum-v1")
    try:
        driver.play(env, 11)
        second = driver.play(env, 12)
    finally:
        for end in ends.values():
            end.close()
        env.close()
    alone = make_aec_env(run.recipe, active=["slow"], evaluation=True, keep_trace=True)
    run_episode(alone, run.learners, 12)
    assert len(driver.faults) == 1
    np.testing.assert_array_equal(second.actions, np.asarray([r.action for r in alone.trace], np.float32))


def test_a_stalled_layer_is_noticed_within_its_period_and_stop_ends_the_deployment(tmp_path):
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    lines = []
    speed = 2.5  # base steps of 20 ms: the fast layer's period, and the floor of a stall
    settings = [Settings(speed=s, faults={"fast": Fault("stall", 20)}, on_fault="stop") for s in (speed, 2 * speed)]
    [row] = deploy(run, settings, episodes=2, out=tmp_path / "deploy", notify=lines.append)  # the second not played
    assert len(lines) == 3 and "stalled" in lines[0] and "stopping" in lines[0]
    assert lines[2] == "the deployment ends (--on-fault stop): 5x not played"
    assert row["episodes"] == 0 and len(row["faults"]) == 1 and not (tmp_path / "deploy" / "5x.json").exists()
    assert (row["transport"], row["weights"], row["threshold"], row["episodes_asked"]) == ("process", "best", None, 2)
    noticed = int(lines[0].split(" at step ")[1].split()[0])
    # the 20th request is step 19's; its deadline is the end of step 19, a stall one period (one step) past it
    assert 20 <= noticed <= 19 + 1 + 1 + 3  # (and up to 3 steps of the OS's scheduling)
    assert not any(_alive(pid) for pid in row["pids"])


def test_a_message_of_another_protocol_version_is_refused_both_ways(tmp_path, monkeypatch):
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    from layered.export import export_stack

    directory = export_stack(run.recipe, run.learners, run.active, tmp_path / "export", "torchscript")
    process = LayerProcess("fast", directory, "torchscript")
    process.wait_ready(60)
    view = np.zeros(json.loads((directory / "stack.json").read_text())["observation_dims"]["fast"], np.float32)
    monkeypatch.setattr(layer_process, "PROTOCOL", 2)  # the driver now speaks version 2, the process version 1
    process.send(Request(1, "fast", 0, 0, view))
    with pytest.raises(LayerFault, match="protocol version 1; this driver speaks version 2"):
        process.receive(10)
    process.send(Request(2, "fast", 0, 1, view))
    with pytest.raises(LayerFault, match="refused a request of protocol version 2; this layer speaks version 1"):
        process.receive(10)
    process.process.join(60)  # (at once on an idle machine; its interpreter's exit can take seconds on a busy one)
    assert process.process.exitcode == 0  # it refused and left
    process.close()


# --- the command ----------------------------------------------------------------------------------------


def test_a_ctrl_c_while_a_layer_process_starts_is_left_to_the_driver(tmp_path):
    """The signal reaches the process while its interpreter imports (before `serve` runs, a second or more): it
    must neither die nor print a traceback, as Ctrl-C at a terminal reaches the whole process group."""
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    from layered.export import export_stack

    directory = export_stack(run.recipe, run.learners, run.active, tmp_path / "export", "torchscript")
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal, even in a background job
    try:
        process = LayerProcess("fast", directory, "torchscript")
    finally:
        signal.signal(signal.SIGINT, before)
    os.kill(process.pid, signal.SIGINT)
    process.wait_ready(60)  # it started all the same
    assert process.process.is_alive()
    process.close()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A briefly trained TLA-C run, shared by the command's tests (they only read it, or write under --out)."""
    out = tmp_path_factory.mktemp("deploy") / "run"
    tiny = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50", "eval.every=100",
            "eval.episodes=1", "eval.fresh_episodes=2"]
    assert main(["train", "pendulum/tla-c.toml", "--out", str(out), "--steps", "150", *tiny]) == 0
    return out


def test_deploy_command_writes_what_it_prints_and_leaves_no_process(trained, tmp_path, capsys):
    out = trained
    before = signal.getsignal(signal.SIGTERM)
    assert main(["deploy", str(out), "--lockstep", "--speed", "5", "--episodes", "1",
                 "--link-delay", "slow=1ms±0.5ms", "--out", str(tmp_path / "d")]) == 0
    assert signal.getsignal(signal.SIGTERM) is before  # its handler, for the deployment only, is gone
    printed = capsys.readouterr().out
    rows = [json.loads((tmp_path / "d" / f"{label}.json").read_text()) for label in ("lockstep,slow=1ms±0.5ms",
                                                                                    "5x,slow=1ms±0.5ms")]
    assert rows[0]["same_actions_as_eval"]
    assert rows[1]["real_time_factor"] == pytest.approx(5, rel=0.5) and rows[1]["steps"] == 200
    assert rows[0]["layers"]["slow"]["latency_ms"]["median"] >= 1.0  # the link's two ways, 0.5 ms at least each
    assert rows[0]["layers"]["slow"]["to_layer_ms"]["median"] >= 0.5
    assert f"{rows[1]['return_mean']:.1f}" in printed and (tmp_path / "d" / "deploy.png").exists()
    assert (tmp_path / "d" / "deploy.md").read_text().strip() in printed
    assert not any(_alive(pid) for row in rows for pid in row["pids"])


@pytest.mark.parametrize(("args", "message"), [
    (["--link-delay", "mid=5ms"], "name a layer of this stack (slow, fast)"),
    (["--fault", "fast:hang@3"], "die@N or stall@N"),
    (["--link-delay", "5"], "is not a duration"),
    (["--link-delay", "5ms", "--transport", "ray"], "with Ray actors the network's own delays apply"),
    (["--link-delay", "slow=5ms", "--link-delay", "slow=6ms"], "--link-delay: layer 'slow' is given twice"),
    (["--link-delay", "5ms", "--link-delay", "6ms"], "--link-delay: 2 values for every layer; give one"),
    (["--fault", "fast:die@3", "--fault", "fast:stall@5"], "--fault: layer 'fast' is given twice"),
])
def test_bad_deploy_options_are_refused_in_one_line(trained, capsys, args, message):
    out = trained
    capsys.readouterr()
    assert main(["deploy", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (out / "deploy").exists()


def test_a_speed_that_is_not_a_positive_number_is_a_usage_error(trained, capsys):
    for speed in ("max", "0", "inf"):
        with pytest.raises(SystemExit) as stop:
            main(["deploy", str(trained), "--speed", f"1,{speed}"])
        assert stop.value.code == 2 and "argument --speed" in capsys.readouterr().err


def _interruptible():
    """In the child before it starts: Ctrl-C as at a terminal, even where this test runs in the background
    (a shell's background jobs inherit SIGINT ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_stops_the_driver_and_every_layer_process(trained, tmp_path, signum):
    out = tmp_path / "deploy"
    command = [sys.executable, "-m", "layered.cli", "deploy", str(trained), "--speed", "1", "--episodes", "20",
               "--out", str(out)]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True, preexec_fn=_interruptible)
    deadline = time.monotonic() + 120
    while not (out / "export-torchscript" / "stack.json").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(8)  # the layers' processes start (a few seconds) and play
    if signum == signal.SIGINT:
        os.killpg(process.pid, signal.SIGINT)  # as Ctrl-C at a terminal: the whole foreground group
    else:
        os.kill(process.pid, signal.SIGTERM)  # as a process manager stops the driver alone
    _, err = process.communicate(timeout=30)
    assert process.returncode == (130 if signum == signal.SIGINT else 143), err
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and last.startswith("layered: stopped" if signum == signal.SIGINT else
                                                      "layered: SIGTERM: stopped at once")
    assert "every layer's process" in last
    deadline = time.monotonic() + 10  # multiprocessing's resource tracker leaves when it sees the driver gone
    while time.monotonic() < deadline:
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            break  # no process of its group is left
        time.sleep(0.1)
    else:
        pytest.fail("a process of the deployment outlived it")


@pytest.mark.slow  # about a minute: Ray starts its own services, and each actor imports torch
def test_layers_as_ray_actors_act_as_processes_do_and_a_dead_actor_is_a_fault(tmp_path):
    pytest.importorskip("ray")
    run = untrained("research/pendulum-residual-3.toml", [], tmp_path)
    lines = []
    rows = deploy(run, [Settings(lockstep=True), Settings(lockstep=True, faults={"mid": Fault("die", 10)})],
                  episodes=1, out=tmp_path / "deploy", notify=lines.append, transport="ray")
    assert rows[0]["same_actions_as_eval"] and not rows[0]["faults"]
    assert len(rows[1]["faults"]) == 1 and "layer 'mid'" in rows[1]["faults"][0] and "died" in rows[1]["faults"][0]
    assert rows[1]["layers"]["mid"]["requests"] == 10


def test_a_setting_that_would_take_long_against_the_clock_says_so_before_it_starts(tmp_path):
    """At 1/20 of real time Pendulum's two episodes of 200 steps of 0.05 s take up to 400 s; cut short by a fault."""
    run = untrained("pendulum/tla-c.toml", [], tmp_path)
    lines = []
    deploy(run, [Settings(speed=0.05, faults={"fast": Fault("die", 2)}, on_fault="stop")], episodes=2,
           out=tmp_path / "deploy", notify=lines.append)
    assert lines[0] == "0.05x: 2 episodes of up to 200 steps at 1 s a step take up to 6.7 minutes"


def test_a_setting_is_named_in_the_figure_with_the_speed_it_reached_where_it_fell_short():
    from layered.deploy_run import _reached

    row = {"setting": "20x", "lockstep": False, "speed": 20.0, "real_time_factor": 13.26}
    assert _reached(row) == "20x (13.3x reached)"
    assert _reached({**row, "real_time_factor": 18.5}) == "20x"  # within a tenth of it
    assert _reached({**row, "setting": "lockstep", "lockstep": True}) == "lockstep"
