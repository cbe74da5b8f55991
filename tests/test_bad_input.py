"""Every bad input is refused before anything is written: exit 2, one line, no traceback."""

from pathlib import Path

import pytest

from layered.cli import main

RECIPES = Path(__file__).parent.parent / "recipes"
TLA_C = RECIPES / "pendulum" / "tla-c.toml"
TLA_O = RECIPES / "pendulum" / "tla-o.toml"
TLA_J = RECIPES / "pendulum" / "tla-joint.toml"


def files(tmp_path: Path) -> dict[str, str]:
    """A recipe directory of the bad kinds a user can hand over."""
    tmp_path.mkdir()
    (tmp_path / "latin1.toml").write_bytes("# r\xe9glage\n[env]\nid = 'Pendulum-v1'\n".encode("latin-1"))
    (tmp_path / "folder.toml").mkdir()
    (tmp_path / "cartpole.toml").write_text('[env]\nid = "CartPole-v1"\n[[layers]]\nname = "a"\nperiod = 1\n')
    (tmp_path / "a-file").write_text("not a directory")
    (tmp_path / "extends-nothing.toml").write_text('extends = "nope.toml"\n')
    for seed in (10, 2, 0):  # a group's directory: the runs of its seeds (their run.json empty)
        (tmp_path / "group" / f"seed{seed}").mkdir(parents=True)
        for name in ("recipe.toml", "run.json"):
            (tmp_path / "group" / f"seed{seed}" / name).write_text("")
    for seed in (10, 2, 0):  # a sweep's setup: runs of the seeds, each trained alone
        (tmp_path / "sweep" / f"seed{seed}").mkdir(parents=True)
        (tmp_path / "sweep" / f"seed{seed}" / "recipe.toml").write_text("")
        (tmp_path / "sweep" / f"seed{seed}" / "run.json").write_text('{"label": "x", "max_steps": null, "plugins": []}')
    return {"tmp": str(tmp_path)}


CASES = {
    "recipe not UTF-8": (["train", "{tmp}/latin1.toml"], "not UTF-8 text"),
    "recipe is a directory": (["train", "{tmp}/folder.toml"], "is a directory, not a recipe file"),
    "missing recipe": (["train", "{tmp}/nope.toml"], "no such recipe file"),
    "extending a missing recipe": (["train", "{tmp}/extends-nothing.toml"],
                                   "extends-nothing.toml: extends: no such recipe file: "),
    "discrete action space": (["train", "{tmp}/cartpole.toml"], "action space is Discrete"),
    "gate learner without a gate": (["train", str(TLA_C), "layers.slow.learner.kind=td3-gate"],
                                    "learner 'td3-gate' cannot drive layer 'slow'"),
    "temporl without repeats": (["train", str(TLA_O), "layers.fast.learner.kind=temporl"],
                                "learner 'temporl' cannot drive layer 'fast'"),
    "learning from commits without a gate above": (["train", str(TLA_C), "layers.fast.learn_from_commits=true"],
                                                   "only the layer right below a gate can learn from its commits"),
    "learning from commits with a delay": (["train", str(TLA_J), "layers.fast.learn_from_commits=true",
                                            "layers.fast.delay=1"], "it needs delay 0, max_repeat 1"),
    "seeing beside outputs in flight without a delay": (["train", str(TLA_C), "layers.fast.sees_in_flight=true"],
                                                        "layers[1].sees_in_flight"),
    "seeing outputs in flight as executed without a delay": (["train", str(TLA_C), "layers.fast.sees_executed=true"],
                                                             "layers[1].sees_executed"),
    "a penalty from the decision without a delay": (["train", str(TLA_C), "layers.fast.action_penalty_from=decision"],
                                                    "layers[1].action_penalty_from"),
    "zero updates per decision": (["train", str(TLA_C), "layers.fast.updates=0"], "layers[1].updates"),
    "unknown plugin": (["train", str(TLA_C), "--plugin", "{tmp}/nope.py"], "plugin"),
    "a setting given to resume as train takes it": (["resume", "{tmp}/run", "layers.fast.learner.lr=1e-4"],
                                                     "(a stopped run's setting is changed with --set KEY=VALUE)"),
    "a sweep given a range of seeds": (["sweep", str(TLA_C), "--seeds", "0-1"],
                                       "a sweep takes a count N (seeds 0..N-1), got '0-1'"),
    "a Ray address without Ray": (["sweep", str(TLA_C), "--address", "10.0.0.1:6379"],
                                  "--address names a Ray cluster: give it with --backend ray"),
    "start weights that are not there": (["train", str(TLA_C), "layers.slow.weights={tmp}/nope.pt"],
                                         "tla-c.toml (with command-line overrides): layers[0].weights: "),
    "zero steps": (["train", str(TLA_C), "--steps", "0"], "--steps: must be positive"),
    "steps not a number": (["train", str(TLA_C), "--steps", "lots"], "--steps: expected a whole number"),
    "zero threads": (["train", str(TLA_C), "--threads", "0"], "--threads: must be positive"),
    "negative seed": (["train", str(TLA_C), "--seed", "-1"], "train.seed"),
    "unknown key": (["train", str(TLA_C), "train.warmpu=5"], "train.warmpu: unknown key"),
    "a gate's reward shaping on a layer that gates nothing": (["train", str(TLA_C), "layers.slow.defer_penalty=3"],
                                                              "layers[0].defer_penalty: it shapes a gate's rewards"),
    "a threshold on the fastest layer": (["train", str(TLA_C), "layers.fast.eval_threshold=0"],
                                         "layers[1].eval_threshold: it thresholds the contributions"),
    "a threshold on a gate": (["train", str(TLA_O), "layers.slow.eval_threshold=0.5"],
                              "thresholds none (its combiner is 'gate')"),
    "a repeating layer with a delay": (["train", str(RECIPES / "pendulum" / "temporl.toml"), "layers.fast.delay=1"],
                                       "layers[0].max_repeat: a layer that chooses how long to hold its output"),
    "a seed twice": (["train", str(TLA_C), "--seed", "3", "train.seed=4"],
                     "give the seed once: --seed or train.seed=4"),
    "a group's seeds and a seed": (["train", str(TLA_C), "--seeds", "2", "train.seed=4"],
                                   "give the seed once: --seeds or train.seed=4"),
    "a sweep's seed": (["sweep", str(TLA_C), "train.seed=5", "--seeds", "1"], "a sweep gives each run its seed"),
    "empty hidden layer": (["train", str(TLA_C), "learner.hidden=[0, 8]"], "learner.hidden[0]"),
    "negative env threads": (["train", str(TLA_C), "env.threads=-1"], "give a number of threads, 0 or more"),
    "env workers as a word": (["train", str(TLA_C), 'env.workers="many"'], "give a number of processes, 0 or more"),
    "reversed return range": (["train", str(TLA_C), "env.return_range=[0, -10]"], "worst return must be below"),
    "out is a file": (["train", str(TLA_C), "--out", "{tmp}/a-file"], "is a file, not a directory"),
    "unknown option": (["train", str(TLA_C), "--stpes", "5"], "unrecognized arguments: --stpes"),
    "resume a non-run": (["resume", "{tmp}"], "is not a run directory"),
    "eval a sweep's directory": (["eval", "{tmp}/sweep"], "it holds the runs seed0, seed2, seed10: name one of them"),
    "eval a group of damaged runs": (["eval", "{tmp}/group"], "seed0/run.json is damaged"),
    "export a group's directory": (["export", "{tmp}/group"], "group/seed0)"),
    "eval a non-run": (["eval", "{tmp}"], "is not a run directory"),
    "eval a missing directory": (["eval", "{tmp}/nope"], "nope: no such directory"),
    "report into a file": (["report", "{tmp}/sweep", "--no-extra-evals", "--out", "{tmp}/a-file"],
                           "a-file: is a file, not a directory"),
    "eval zero episodes": (["eval", "{tmp}", "--episodes", "0"], "--episodes: must be positive"),
    "sweep zero seeds": (["sweep", str(TLA_C), "--seeds", "0"], "--seeds: must be positive"),
    "a group of zero seeds": (["train", str(TLA_C), "--seeds", "0"], "a count N trains seeds 0..N-1, so it is at"),
    "a descending range of seeds": (["train", str(TLA_C), "--seeds", "5-3"],
                                    "--seeds: a range A-B needs A at most B, got '5-3'"),
    "a period written as a string": (["train", str(TLA_C), 'layers.fast.period="1"'],
                                     "layers[1].period: input should be a valid integer"),
    "a whole number written as a float": (["train", str(TLA_C), "train.steps_per_phase=3e4"],
                                          "train.steps_per_phase: input should be a valid integer"),
    "a flag written as a string": (["train", str(TLA_C), 'combine.per_dimension="yes"'],
                                   "combine.per_dimension: input should be a valid boolean"),
    "an infinite threshold in a recipe": (["train", str(TLA_C), "combine.eval_threshold=inf"],
                                          "combine.eval_threshold: input should be a finite number"),
    "a learning rate of nan": (["train", str(TLA_C), "learner.lr=nan"], "learner.lr: input should be a finite number"),
    "a seed beyond 32 bits": (["train", str(TLA_C), "--seed", str(2**64)], "train.seed: input should be less than"),
    "eval threshold nan": (["eval", "{tmp}", "--threshold", "nan"], "a threshold is a finite number >= 0"),
    "eval threshold sweep with inf": (["eval", "{tmp}", "--threshold-sweep", "0,inf"], "a threshold is a finite"),
    "export threshold nan": (["export", "{tmp}", "--threshold", "nan"], "a threshold is a finite number >= 0"),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_input_exits_2_with_one_line_and_writes_nothing(case, tmp_path, capsys, monkeypatch):
    values = files(tmp_path / "in")
    monkeypatch.chdir(tmp_path)  # a default run directory would land in ./runs
    argv, says = CASES[case]
    argv = [a.format(**values) for a in argv]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    try:
        code = main([*argv, *(["--out", str(tmp_path / "out")] if argv[0] == "train" and "--out" not in argv else [])])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.strip().splitlines() if not line.startswith("training ")]  # (what it was to start)
    assert says in err and len(lines) == 1 and lines[0].startswith("layered: error: ") and "Traceback" not in err, err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_a_budget_below_a_layers_warm_up_is_named_before_training(tmp_path, capsys):
    code = main(["train", str(TLA_C), "learner.hidden=[8]", "eval.episodes=1", "eval.fresh_episodes=1",
                 "--steps", "300", "--out", str(tmp_path / "run"), "--threads", "1"])
    err = capsys.readouterr().err
    assert code == 0
    warning = "layered: warning: phase 0 runs 300 steps, but layer 'slow' acts at random for its first 1000 decisions"
    assert err.index(warning) < err.index("phase 0: slow") and "(lower train.warmup or raise the steps)" in err


def test_the_warm_up_warning_names_the_key_that_sets_the_layers_warm_up():
    from layered.recipe import load_recipe
    from layered.runs import warmup_warnings

    own, shared = warmup_warnings(load_recipe(TLA_C, ["layers.slow.warmup=500"]), 300)
    assert "'slow' acts at random for its first 500 decisions" in own
    assert own.endswith("(lower layers.slow.warmup or raise the steps)")
    assert "'fast'" in shared and shared.endswith("(lower train.warmup or raise the steps)")


def test_a_single_run_given_settings_of_a_groups_environments_is_told_they_change_nothing():
    from layered.recipe import load_recipe
    from layered.runs import group_only_settings

    assert group_only_settings(load_recipe(TLA_C)) == []
    assert group_only_settings(load_recipe(TLA_C, ["env.threads=2"])) == []  # (its evaluations step in threads)
    said = group_only_settings(load_recipe(TLA_C, ["env.workers=2", "env.wait=spin"]))
    assert len(said) == 1 and said[0].startswith("env.workers and env.wait set how a group's environments step")


def test_report_names_a_broken_run_and_reports_the_others(tmp_path, tiny, capsys):
    good, broken = tmp_path / "runs" / "good", tmp_path / "runs" / "broken"
    assert main(["train", str(TLA_C), *tiny, "--steps", "200", "--out", str(good), "--threads", "1"]) == 0
    broken.mkdir()
    (broken / "results.json").write_text('{"phases": [')
    capsys.readouterr()
    assert main(["report", str(tmp_path / "runs"), "--no-extra-evals", "--out", str(tmp_path / "report")]) == 0
    err = capsys.readouterr().err
    assert f"{broken}: its results cannot be read (JSONDecodeError" in err and "Traceback" not in err
    assert "| Pendulum-v1 |" in (tmp_path / "report" / "report.md").read_text()
    (good / "results.json").write_text("{}")
    assert main(["report", str(tmp_path / "runs"), "--no-extra-evals"]) == 2
    assert "no readable finished run" in capsys.readouterr().err


def test_ctrl_c_while_the_command_starts_is_one_line(tmp_path):
    """SIGINT while the command line loads (torch takes a moment): one line, exit 130, no traceback."""
    import signal
    import subprocess
    import sys
    import time

    script = ("import sys; from layered.command import main; print('ready', file=sys.stderr, flush=True); "
              "sys.argv[0] = 'layered'; sys.exit(main())")
    proc = subprocess.Popen([sys.executable, "-c", script, "train", str(TLA_C), "--out", str(tmp_path / "run")],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as at a terminal
    assert proc.stderr.readline().strip() == "ready"
    time.sleep(0.3)  # into main, which then loads torch (seconds), not in the two statements before it
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("layered: stopped")


def test_ctrl_c_that_a_library_swallows_while_the_command_starts_still_stops_it(monkeypatch, capsys):
    """A KeyboardInterrupt raised while modules load can be swallowed by the module being loaded (a bare
    `except`, a finaliser): the command must stop all the same, with one line, before running anything."""
    import os
    import signal

    import layered.cli
    from layered import command

    def swallowing_load(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)  # handled at once, in this thread
        except BaseException:  # what a library's loading code may do
            pass

    ran, before = [], signal.getsignal(signal.SIGINT)
    monkeypatch.setattr(layered.cli, "load", swallowing_load)
    monkeypatch.setattr(layered.cli, "run", ran.append)
    monkeypatch.setattr("sys.argv", ["layered", "train", str(TLA_C)])
    assert command.main() == 130 and not ran
    assert capsys.readouterr().err.strip() == "layered: stopped while starting; nothing was written"
    assert signal.getsignal(signal.SIGINT) is before  # put back


def test_a_second_ctrl_c_while_the_command_starts_stops_at_once():
    """The first SIGINT while loading is held for the end of loading; a second one raises at once (a load
    that hangs can still be interrupted)."""
    import os
    import signal

    from layered.command import sigint_held

    with pytest.raises(KeyboardInterrupt), sigint_held() as received:
        os.kill(os.getpid(), signal.SIGINT)
        assert received == [signal.SIGINT]
        os.kill(os.getpid(), signal.SIGINT)
        pytest.fail("the second SIGINT did not raise")


def test_help_version_and_usage_errors_answer_without_loading_torch_and_a_command_loads_what_it_runs_on():
    """`layered --help`, `--version` and a usage error come from the command line alone (torch takes seconds
    to load); `load` imports what the parsed command runs on. One fresh interpreter runs them in turn."""
    import json
    import subprocess
    import sys

    from layered import __version__

    script = """import contextlib, io, json, sys
from layered.cli import load, parse
said = []
for argv in (["--help"], ["--version"], ["train", "--seeds", "0-"]):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            parse(argv)
        except SystemExit as e:
            said.append([e.code, out.getvalue(), err.getvalue(), "torch" in sys.modules])
load(parse(["report", "runs"]))
said.append("torch" in sys.modules)
load(parse(["train", "pendulum/td3"]))
said.append("torch" in sys.modules)
print(json.dumps(said))"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    helped, version, refused, after_report, after_train = json.loads(out.stdout)
    assert helped[0] == 0 and helped[1].startswith("usage: layered") and not helped[3]
    assert version == [0, f"layered {__version__}\n", "", False]
    assert refused[0] == 2 and not refused[3]
    assert "--seeds: expected N, A-B or A,B,C, got '0-'" in refused[2]  # (not "a whole number")
    assert (after_report, after_train) == (False, True)


def test_the_package_names_load_when_first_used_and_are_what_their_modules_define():
    """`import layered` loads neither torch nor an environment; each public name resolves to its home's."""
    import importlib
    import subprocess
    import sys

    import layered

    script = "import sys, layered; print('torch' in sys.modules, 'gymnasium' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["False", "False"], out.stderr
    for name in layered.__all__:
        assert getattr(layered, name) is getattr(importlib.import_module(layered._HOMES[name]), name)
    assert issubclass(layered.RecipeError, layered.BadInput)


def test_a_bare_layered_prints_what_it_can_do(capsys):
    with pytest.raises(SystemExit) as stop:
        main([])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith("usage: layered") and "{train,resume,eval" in err


@pytest.mark.parametrize("option", ["--gallery", "--threshold-sweep"])
def test_an_optional_value_that_is_a_run_directory_is_taken_as_the_run(option, tmp_path):
    """`eval --gallery RUN` would read RUN as the layer's name (and `--threshold-sweep RUN` as thresholds); a run's or
    a group's directory there is the run, and a value that is no run's stays the option's."""
    from layered.cli import parse

    run, group = tmp_path / "run", tmp_path / "group"
    for marker in (run / "run.json", group / "seed0" / "run.json"):
        marker.parent.mkdir(parents=True)
        marker.write_text("{}")
    for directory in (run, group):
        args = parse(["eval", option, str(directory), "--episodes", "2"])
        assert args.run_dir == directory and args.episodes == 2
        assert (args.gallery == "") if option == "--gallery" else (args.threshold_sweep is not None)
    assert parse(["eval", str(run), "--gallery", "fast"]).gallery == "fast"
    assert parse(["eval", str(run), "--threshold-sweep", "0,0.5"]).threshold_sweep == [0.0, 0.5]
    with pytest.raises(SystemExit):  # a directory that holds no run is not taken for one
        parse(["eval", "--gallery", str(tmp_path)])
