"""Reports: aggregation over seeds by hand, and the report command on real runs."""

import contextlib
import csv
import io
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import pytest

from layered import load_recipe
from layered.cli import main
from layered.report import DEFAULT_SWEEP, _steps_axis
from layered.run_evals import kept_thresholds, missing_figure_evals, run_figure_evals
from layered.summary import Run, Setup, find_runs, group
from layered.runs import train

from conftest import stop_at, stop_at_episode_end, train_until_stopped

PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"
TINY = ["learner.hidden=[32, 32]", "learner.batch_size=32", "train.warmup=50",
        "eval.every=100", "eval.episodes=1", "eval.fresh_episodes=2"]


def run(label, seed, ret, auc, curve, env="Pendulum-v1", realtime=False):
    final = {"return_mean": ret, "auc": auc, "repetition": 0.5, "decisions": 200.0}
    return Run(Path(f"/r/{label}-{seed}"), env, label, seed, realtime, final, tuple(curve))


def test_setup_statistics_are_mean_and_population_std_over_seeds():
    s = Setup("Pendulum-v1", "pendulum/td3", (run("pendulum/td3", 0, -100.0, 0.5, [(0, -1000), (10, -100)]),
                                              run("pendulum/td3", 1, -300.0, 0.7, [(0, -1200), (10, -300), (20, 0)])))
    assert s.stat("return_mean") == pytest.approx((-200.0, 100.0))
    assert s.stat("auc") == pytest.approx((0.6, 0.1))
    steps, mean, std, lowest, highest = s.curve()  # only the evaluations both runs made
    assert list(steps) == [0, 10] and list(mean) == [-1100, -200] and list(std) == [100, 100]
    assert list(lowest) == [-1200, -300] and list(highest) == [-1000, -100]
    assert s.method == "td3"


def test_whole_run_curve_lays_phases_end_to_end(tmp_path):
    (tmp_path / "results.json").write_text(json.dumps({"env": "Pendulum-v1", "seed": 0, "label": "p/tla-c",
                                                        "phases": [{"phase": 1, "return_mean": -150.0}]}))
    (tmp_path / "recipe.toml").write_text('[train]\nseed = 0\n[[layers]]\nname = "slow"\n')
    (tmp_path / "metrics.csv").write_text("phase,step,return_mean\n0,0,-900\n0,5001,-400\n0,10002,-200\n"
                                          "1,0,-300\n1,5000,-160\n1,10000,-150\n")
    run_ = find_runs([tmp_path])[0]
    assert run_.curve == ((0, -300.0), (5000, -160.0), (10000, -150.0))
    # the fast phase's first evaluation (-300, the hand-over) is at the slow phase's end, beside its last; its steps
    # follow 10002
    assert run_.total_curve == ((0, -900.0), (5001, -400.0), (10002, -200.0), (10002, -300.0), (15002, -160.0),
                                (20002, -150.0))


def test_a_run_started_from_another_runs_weights_continues_that_runs_steps(tmp_path):
    def write(path, metrics, layers, seed=1):
        path.mkdir(parents=True)
        (path / "results.json").write_text(json.dumps({"env": "Pendulum-v1", "seed": seed, "label": "p/tla-c",
                                                       "phases": [{"phase": 0, "return_mean": -150.0}]}))
        (path / "recipe.toml").write_text(f"[train]\nseed = {seed}\n" + "".join(
            f'[[layers]]\nname = "{name}"\n' + (f'weights = "{w}"\n' if w else "") for name, w in layers))
        (path / "metrics.csv").write_text("phase,learn,step,return_mean\n" + metrics)

    # slow for 10002 steps, then fast for 7000; a third phase that trains the fast layer alone again, 3000
    write(tmp_path / "a" / "seed1", "0,slow,0,-900\n0,slow,10002,-200\n1,fast,0,-300\n1,fast,7000,-160\n"
          "2,fast,0,-160\n2,fast,3000,-150\n", [("slow", None), ("fast", None)])
    # a fast phase over a's slow layer: its steps follow a's phase 0, not a's later phases that left slow alone
    write(tmp_path / "b", "0,fast,0,-250\n0,fast,5000,-140\n",
          [("slow", f"{tmp_path}/a/seed{{seed}}/checkpoints/slow.best.pt"), ("fast", None)])
    # started from b's fast layer (b: 10002 steps behind it, then 5000 of its own) and from a's slow one
    write(tmp_path / "c", "0,fast,0,-140\n0,fast,2500,-130\n1,slow+fast,0,-130\n1,slow+fast,2500,-120\n",
          [("slow", f"{tmp_path}/a/seed1/checkpoints/slow.pt"), ("fast", f"{tmp_path}/b/checkpoints/fast.pt")])
    # a file outside any run directory: nothing known behind it
    write(tmp_path / "d", "0,fast,0,-250\n0,fast,5000,-140\n", [("slow", f"{tmp_path}/slow.pt"), ("fast", None)])
    b, c, d = (find_runs([tmp_path / name])[0] for name in "bcd")
    assert b.trained_before == 10002 and b.total_curve == ((10002, -250.0), (15002, -140.0))
    assert c.trained_before == 15002 and c.total_curve == ((15002, -140.0), (17502, -130.0), (17502, -130.0),
                                                           (20002, -120.0))
    assert c.phase_starts == (17502,)
    assert d.trained_before == 0 and d.total_curve == d.curve == ((0, -250.0), (5000, -140.0))
    # the runs behind each: b and c hold a's slow layer, c b's fast one; d nothing of theirs
    a = find_runs([tmp_path / "a"])[0]
    assert b.started_from == {(tmp_path / "a" / "seed1").resolve()} and not d.started_from
    assert c.started_from == {(tmp_path / "a" / "seed1").resolve(), (tmp_path / "b").resolve()}
    assert a.shares_layers_with(b) and b.shares_layers_with(a) and b.shares_layers_with(c)
    assert not d.shares_layers_with(a) and not a.shares_layers_with(d)
    # the stack each continues: b a's at the end of its phase 0; c two runs' stacks; d none known
    assert b.continues == ((tmp_path / "a" / "seed1").resolve(), 0) and c.continues is None and d.continues is None
    # both layers from a, the fast one from its phase 2: a's stack at that phase's end
    write(tmp_path / "e", "0,slow+fast,0,-150\n0,slow+fast,1000,-140\n",
          [("slow", f"{tmp_path}/a/seed1/checkpoints/slow.pt"), ("fast", f"{tmp_path}/a/seed1/checkpoints/fast.pt")])
    assert find_runs([tmp_path / "e"])[0].continues == ((tmp_path / "a" / "seed1").resolve(), 2)
    # b's slow layer, which b did not train (a's, 10002 steps behind it), with b's fast one: b's stack at the end of
    # its phase 0; b's slow layer alone: a's steps behind it, but none of b's phases trained it, so no stack of b's
    write(tmp_path / "f", "0,fast,0,-140\n0,fast,1000,-135\n",
          [("slow", f"{tmp_path}/b/checkpoints/slow.pt"), ("fast", f"{tmp_path}/b/checkpoints/fast.pt")])
    write(tmp_path / "g", "0,fast,0,-250\n0,fast,1000,-200\n",
          [("slow", f"{tmp_path}/b/checkpoints/slow.pt"), ("fast", None)])
    f, g = (find_runs([tmp_path / name])[0] for name in "fg")
    assert f.continues == ((tmp_path / "b").resolve(), 0) and f.trained_before == 15002
    assert g.continues is None and g.trained_before == 10002 and g.phase_starts == ()
    # a damaged run behind the weights is a warning, not a damaged run here
    (tmp_path / "a" / "seed1" / "metrics.csv").write_text("phase,step\n0,x\n")
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert find_runs([tmp_path / "b"])[0].trained_before == 0
        assert not find_runs([tmp_path / "b"])[0].shares_layers_with(a)
    assert "where layer 'slow' started from, cannot be read" in err.getvalue()


def test_behind_a_layer_a_run_passed_on_untrained_is_only_what_came_in(tmp_path):
    from layered.summary import _phases_until

    # a run with no results yet: nothing known of its phases, but at its start (-1) only its start weights count
    assert _phases_until(tmp_path, 0, []) is None
    assert _phases_until(tmp_path, -1, []) == ()
    (tmp_path / "results.json").write_text(json.dumps({"phases": [{"phase": 0, "auc": 0.5}, {"phase": 1, "auc": 0.7}]}))
    assert _phases_until(tmp_path, 0, []) == ({"phase": 0, "auc": 0.5},)
    assert _phases_until(tmp_path, -1, []) == ()


def test_the_curves_in_numbers_are_read_at_the_evaluations_nearest_each_fraction_of_the_last_phase():
    from layered.report import curve_points, curve_table

    s = Setup("Pendulum-v1", "p/td3", (run("p/td3", 0, 0, 0, [(step, step - 1000) for step in range(0, 1001, 100)]),
                                       run("p/td3", 1, 0, 0, [(step, step - 800) for step in range(0, 1001, 100)])))
    # a quarter (250) and three quarters (750) lie halfway between two evaluations: the earlier one is read
    assert curve_points(s) == [(100, -800, 100), (200, -700, 100), (500, -400, 100), (700, -200, 100),
                               (1000, 100, 100)]
    assert curve_table([s]).splitlines()[2] == (
        "| Pendulum-v1 | td3 | -800.0 ± 100.0 at 100 | -700.0 ± 100.0 at 200 | -400.0 ± 100.0 at 500 "
        "| -200.0 ± 100.0 at 700 | 100.0 ± 100.0 at 1k |")


def test_bands_are_clipped_to_the_return_bounds():
    from layered.report import band

    # three evaluations of returns 1000 (the task's maximum), 700 ± 300 and 100 ± 50
    low, high = band([1000.0, 700.0, 100.0], [0.0, 300.0, 50.0], [1000.0, 200.0, 60.0], [1000.0, 1000.0, 160.0])
    assert list(low) == [1000.0, 400.0, 60.0] and list(high) == [1000.0, 1000.0, 150.0]
    low, high = band([5.0], [10.0])
    assert list(low) == [-5.0] and list(high) == [15.0]


def test_seeds_align_evaluation_by_evaluation_at_their_mean_step():
    a = run("p/tla-c", 0, 0, 0, [])
    s = Setup("Pendulum-v1", "p/tla-c", (
        Run(a.path, a.env, a.label, 0, False, a.final, (), ((0, -900.0), (5001, -400.0), (10002, -200.0))),
        Run(a.path, a.env, a.label, 1, False, a.final, (), ((0, -700.0), (5003, -200.0)))))
    steps, mean, std, _, _ = s.curve(whole_run=True)
    assert list(steps) == [0, 5002] and list(mean) == [-800, -300] and list(std) == [100, 100]


def test_long_setup_names_wrap_in_the_legend_within_their_plot(tmp_path, monkeypatch):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from layered.report import plot_setup_curves

    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *args, **kwargs: drawn.append(fig))
    curve = [(0, -900.0), (5000, -200.0)]
    long = "p/tla-o layers.slow.defer_reward_scale=[2.0, 1.0] train.order=explicit layers.fast.weights=x/seed0"
    plot_setup_curves(group([run("p/td3", 0, 0, 0, curve), run(long, 0, 0, 0, curve)]), tmp_path / "curves.png")
    fig, = drawn
    ax, = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[0] == "td3 (1 seed)" and all(len(line) <= 44 for line in labels[1].splitlines())
    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # (lays the figure out, as saving it would)
    renderer = canvas.get_renderer()
    legend, box = ax.get_legend().get_window_extent(renderer), ax.get_window_extent(renderer)
    assert legend.width < box.width and box.width > fig.bbox.width / 2  # the plot was not squeezed aside


def test_the_whole_run_is_drawn_only_for_an_environment_whose_setups_train_in_phases(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from layered.report import plot_setup_curves

    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *args, **kwargs: drawn.append(fig))
    curve = [(0, -900.0), (5000, -200.0)]
    two_phases = replace(run("p/tla-c", 0, 0, 0, curve), total_curve=((0, -1000.0), (5000, -950.0),
                                                                       (5000, -900.0), (10000, -200.0)),
                         phase_starts=(5000,))
    one_phase = [replace(run(label, 0, 0, 0, curve, env=env), total_curve=tuple(curve))
                 for label, env in (("p/td3", "Pendulum-v1"), ("c/td3", "CartPole"))]
    plot_setup_curves(group([two_phases, *one_phase]), tmp_path / "curves.png")
    fig, = drawn
    last, whole = fig.axes[:2], fig.axes[2:]

    def ends(ax):  # each setup's curve, by its legend's name, at its last step
        named = (line for line in ax.get_lines() if not line.get_label().startswith("_"))
        return {line.get_label(): line.get_xdata()[-1] for line in named}

    column = {ax.get_title(): i for i, ax in enumerate(last)}
    pendulum, cartpole = column["Pendulum-v1: last phase"], column["CartPole: last phase"]
    assert whole[pendulum].get_title() == "Pendulum-v1: whole run"
    marks = [text.get_text() for text in whole[pendulum].texts]
    assert marks == ["phase 1: tla-c"]  # one marker per phase start, naming the setups it is of
    assert ends(last[pendulum]) == {"tla-c (1 seed)": 5000, "td3 (1 seed)": 5000}
    assert ends(whole[pendulum]) == {"tla-c (1 seed)": 10000, "td3 (1 seed)": 5000}
    assert ends(last[cartpole]) == {"td3 (1 seed)": 5000}
    assert not whole[cartpole].axison and not whole[cartpole].get_lines()
    assert "every setup trains in one phase" in whole[cartpole].texts[0].get_text()


def test_grouping_orders_methods_as_the_paper():
    runs = [run("p/tla-c", 0, 0, 0, []), run("p/td3", 0, 0, 0, []), run("p/tla-o", 1, 0, 0, []),
            run("p/tla-c", 1, 0, 0, []), run("p/temporl", 0, 0, 0, [])]
    setups = group(runs)
    assert [s.method for s in setups] == ["td3", "temporl", "tla-o", "tla-c"]
    assert [len(s.runs) for s in setups] == [1, 1, 1, 2]


def test_runs_of_different_recipes_under_one_label_are_setups_of_their_own(capsys):
    from layered.summary import _setting

    def at(seed, penalty, order, older=False, steps=None, group=()):
        recipe = {"env": {"id": "Pendulum-v1"}, "train": {"seed": seed, "order": order},
                  "layers": [{"name": "slow", "period": 4}, {"name": "fast", "action_penalty": penalty}]}
        if not older:
            recipe["train"]["select"] = "best"  # a key older runs lack does not split them
        info = {"max_steps": steps, **({"group": group} if group else {})}
        return replace(run("p/tla-c", seed, 0, 0, []), setting=_setting(recipe, info))

    flat = {"layers.fast.a": "[1, 2]", "trained": "alone"}
    assert dict(_setting({"layers": [{"name": "fast", "a": [1, 2]}], "train": {"seed": 3, "checkpoint_every": 9},
                          "log": {"tensorboard": True}, "env": {"workers": 2}}, {})) == flat
    # explicit phases that each name their steps make `steps_per_phase` inert: it is no setting of the run
    phased = {"train": {"order": "explicit", "steps_per_phase": 9, "phases": [{"learn": ["fast"], "steps": 3}]}}
    assert "train.steps_per_phase" not in dict(_setting(phased, {}))
    phased["train"]["phases"].append({"learn": ["slow"]})  # a phase without steps runs `steps_per_phase` of them
    assert dict(_setting(phased, {}))["train.steps_per_phase"] == "9"
    setups = group([at(0, 1.0, "slow-to-fast"), at(1, 1.0, "slow-to-fast", older=True), at(0, 2.0, "explicit"),
                    at(1, 2.0, "explicit")])
    assert [(s.label, [r.seed for r in s.runs]) for s in setups] == [
        ("p/tla-c layers.fast.action_penalty=1.0 train.order=slow-to-fast", [0, 1]),
        ("p/tla-c layers.fast.action_penalty=2.0 train.order=explicit", [0, 1]),
    ]
    assert [len(s.runs) for s in group([at(0, 1.0, "joint"), at(1, 1.0, "joint")])] == [2]  # the seed alone: one
    # runs capped at another --steps are another setup; a seed from two runs of one setup is named
    assert [(s.label, len(s.runs)) for s in group([at(0, 1.0, "joint", steps=1000), at(0, 1.0, "joint")])] == [
        ("p/tla-c --steps=1000", 1), ("p/tla-c --steps=none", 1)]
    assert "come from more than one run" not in capsys.readouterr().err
    # seeds trained as a group are another setup than the same seeds trained alone; the groups of one sweep are one
    assert [(s.label, len(s.runs)) for s in group([at(0, 1.0, "joint", group=[0, 1]), at(1, 1.0, "joint", group=[0, 1]),
                                                   at(2, 1.0, "joint", group=[2]), at(0, 1.0, "joint")])] == [
        ("p/tla-c trained=alone", 1), ("p/tla-c trained=group", 3)]
    assert "come from more than one run" not in capsys.readouterr().err
    assert [len(s.runs) for s in group([at(0, 1.0, "joint"), at(0, 1.0, "joint"), at(1, 1.0, "joint")])] == [3]
    assert "tla-c: seed 0 comes from more than one run of the same setup (seed 0: /r/p/tla-c-0, /r/p/tla-c-0)" in \
        capsys.readouterr().err
    # a key unset by default is left out of a resolved recipe while unset: a layer started from weights is apart
    started = replace(at(1, 1.0, "joint"), setting=(*at(1, 1.0, "joint").setting, ("layers.slow.weights", "w.pt")))
    assert [s.label for s in group([at(0, 1.0, "joint"), started, at(2, 1.0, "joint", older=True)])] == [
        "p/tla-c layers.slow.weights=unset", "p/tla-c layers.slow.weights=w.pt"]
    # a long value that another key already tells apart is left out of the label (the Runs table names it); a
    # path in it does not change the method
    path = "/home/me/runs/slow-layers/seed{seed}/checkpoints/slow.best.pt"
    probe = replace(at(1, 2.0, "joint"), setting=(*at(1, 2.0, "joint").setting, ("layers.slow.weights", path)))
    setups = group([at(0, 1.0, "joint"), probe])
    assert [(s.label, s.method, s.runs[0].unnamed) for s in setups] == [
        ("p/tla-c layers.fast.action_penalty=1.0", "tla-c layers.fast.action_penalty=1.0",
         ("layers.slow.weights=unset",)),
        ("p/tla-c layers.fast.action_penalty=2.0", "tla-c layers.fast.action_penalty=2.0",
         (f"layers.slow.weights={path}",))]
    from layered.report import seeds_table
    assert f"| p/tla-c layers.fast.action_penalty=2.0 (layers.slow.weights={path}) | 1 |" in seeds_table(setups,
                                                                                                         Path("."))
    alone = replace(at(1, 1.0, "joint"), setting=(*at(1, 1.0, "joint").setting, ("layers.slow.weights", path)))
    # where nothing else tells them apart, the long value names the setup
    assert f"p/tla-c layers.slow.weights={path}" in [s.label for s in group([at(0, 1.0, "joint"), alone])]


def test_report_command_on_real_runs(tmp_path):
    for name, seed in (("td3", 0), ("td3", 1), ("tla-c", 0)):
        recipe = load_recipe(PENDULUM / f"{name}.toml", [*TINY, f"train.seed={seed}"])
        train(recipe, tmp_path / "runs" / f"{name}-s{seed}", max_steps=200, progress=False, label=f"pendulum/{name}")
    finals = {p.name: json.loads((p / "results.json").read_text())["phases"][-1]
              for p in (tmp_path / "runs").iterdir()}
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(tmp_path / "runs"),
                           "--out", str(tmp_path / "report")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    returns = [finals["td3-s0"]["return_mean"], finals["td3-s1"]["return_mean"]]
    mean, std = sum(returns) / 2, abs(returns[0] - returns[1]) / 2
    assert f"{mean:.1f} ± {std:.1f}" in proc.stdout
    assert f"{finals['tla-c-s0']['repetition']:.1%} (1 seed)" in proc.stdout
    assert (tmp_path / "report" / "curves.png").stat().st_size > 0
    assert len(find_runs([tmp_path / "runs"])) == 3
    assert "pendulum/td3,td3,0 1," in (tmp_path / "report" / "summary.csv").read_text()
    points = [line.split(",") for line in (tmp_path / "report" / "curves.csv").read_text().splitlines()[1:]]
    td3 = [(float(row[5]), float(row[6])) for row in points if row[2] == "td3" and row[4] == "last phase"]
    curves = [[(float(r["step"]), float(r["return_mean"])) for r in csv.DictReader(
        (tmp_path / "runs" / f"td3-s{seed}" / "metrics.csv").open())] for seed in (0, 1)]
    assert td3 == [((a[0] + b[0]) / 2, pytest.approx((a[1] + b[1]) / 2)) for a, b in zip(*curves, strict=True)]
    assert {row[4] for row in points if row[2] == "tla-c"} == {"last phase", "whole run"}
    phases = [line.split(",")[:6] for line in (tmp_path / "report" / "seeds.csv").read_text().splitlines()[1:]]
    assert [row[1:] for row in phases] == [
        ["pendulum/td3", "td3", "0", "0", "fast"], ["pendulum/td3", "td3", "1", "0", "fast"],
        ["pendulum/tla-c", "tla-c", "0", "0", "slow"], ["pendulum/tla-c", "tla-c", "0", "1", "fast"]]
    # the evaluations behind Fig. 2 and the gallery ran once, for the stack with a threshold and two layers
    assert "[1/1] " in proc.stderr and "tla-c-s0: evaluating threshold sweep and gallery" in proc.stderr
    assert sorted(p.name for p in (tmp_path / "runs" / "tla-c-s0" / "eval").iterdir()) == [
        "gallery-fast.png", "threshold-sweep.csv"]
    assert not (tmp_path / "runs" / "td3-s0" / "eval").exists()
    report = (tmp_path / "report" / "report.md").read_text()
    assert "threshold-Pendulum-v1-tla-c.png" in report and "gallery-Pendulum-v1-tla-c.png" in report
    assert "| Pendulum-v1 | pendulum/tla-c | 0 | ../runs/tla-c-s0 |" in report  # (followed from the report's folder)
    assert [row["run"] for row in csv.DictReader((tmp_path / "report" / "seeds.csv").open())] == [
        "../runs/td3-s0", "../runs/td3-s1", "../runs/tla-c-s0", "../runs/tla-c-s0"]
    sweep = list(csv.DictReader((tmp_path / "report" / "threshold-Pendulum-v1-tla-c.csv").open()))
    kept = list(csv.DictReader((tmp_path / "runs" / "tla-c-s0" / "eval" / "threshold-sweep.csv").open()))
    assert [float(row["return_mean"]) for row in sweep] == [float(row["return_mean"]) for row in kept]  # one seed
    again = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(tmp_path / "runs"),
                            "--out", str(tmp_path / "report2")], capture_output=True, text=True)
    assert again.returncode == 0 and "evaluating" not in again.stderr  # kept in the runs, reused


def test_report_without_extra_evaluations_runs_none(tmp_path):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "run", max_steps=200, progress=False)
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(tmp_path / "run"),
                           "--out", str(tmp_path / "report"), "--no-extra-evals"], capture_output=True, text=True)
    assert proc.returncode == 0 and not (tmp_path / "run" / "eval").exists()


def test_a_sweep_of_other_thresholds_keeps_a_name_of_its_own_and_never_stands_in_for_fig_2(tmp_path):
    recipe = load_recipe(PENDULUM / "tla-c.toml", TINY)
    train(recipe, tmp_path / "run", max_steps=200, progress=False)
    eval_dir = tmp_path / "run" / "eval"
    assert main(["eval", str(tmp_path / "run"), "--episodes", "1", "--threshold-sweep", "0,0.3"]) == 0
    assert sorted(p.name for p in eval_dir.iterdir()) == ["threshold-sweep-0-0.3.csv", "threshold-sweep-0-0.3.png"]
    assert missing_figure_evals(tmp_path / "run") == ["threshold sweep", "gallery"]
    # one kept where the default grid's goes (as `layered eval` kept it before): moved aside, then the grid run
    (eval_dir / "threshold-sweep-0-0.3.csv").rename(eval_dir / "threshold-sweep.csv")
    before = (eval_dir / "threshold-sweep.csv").read_text()
    run_figure_evals(tmp_path / "run", ["threshold sweep"])
    assert (eval_dir / "threshold-sweep-0-0.3.csv").read_text() == before
    assert kept_thresholds(eval_dir / "threshold-sweep.csv") == DEFAULT_SWEEP
    assert missing_figure_evals(tmp_path / "run") == ["gallery"]


def test_an_unfinished_run_is_taken_at_its_last_evaluation_only_when_asked(tmp_path):
    run_dir = tmp_path / "runs" / "group" / "seed3"
    run_dir.mkdir(parents=True)
    (run_dir / "recipe.toml").write_text('[env]\nid = "Hopper-v5"\n[train]\nseed = 3\n'
                                         '[[layers]]\nname = "slow"\ndelay = 1\n')
    (run_dir / "run.json").write_text(json.dumps({"label": "hopper/tla-realtime", "group": [3]}))
    (run_dir / "metrics.csv").write_text("phase,learn,step,return_mean,repetition,critic_loss_slow\n"
                                         "0,slow,0,100,0.5,\n0,slow,5000,300,0.5,2.5\n1,fast,0,280,0.4,\n"
                                         "1,fast,5000,350,0.25,1.5\n1,fast,10000,350,0.2,1.25\n1,fast,15000,90,0.2,1\n")
    with pytest.raises(FileNotFoundError, match="1 run in it not finished: --unfinished reports them"):
        find_runs([tmp_path / "runs"])
    (run_,) = find_runs([tmp_path / "runs"], unfinished=True)
    assert not run_.finished and run_.stands == "phase 1, step 15000"
    assert (run_.env, run_.label, run_.seed, run_.realtime) == ("Hopper-v5", "hopper/tla-realtime", 3, True)
    assert run_.method == "tla-realtime (unfinished)"
    # its last evaluation, and its best so far: the earlier of two of 350 (the evaluation whose weights it keeps)
    assert run_.final == {"step": 15000.0, "return_mean": 90.0, "repetition": 0.2, "critic_loss_slow": 1.0,
                          "phase": 1, "best_step": 5000, "best_return_mean": 350.0}
    assert run_.curve == ((0, 280.0), (5000, 350.0), (10000, 350.0), (15000, 90.0)) and run_.phase_starts == (5000,)
    (run_dir / "metrics.csv").write_text("phase,learn,step,return_mean\n")  # started, not yet evaluated
    with pytest.raises(FileNotFoundError, match="no readable run"):
        find_runs([tmp_path / "runs"], unfinished=True)


def test_report_of_a_stopped_run_beside_a_finished_one(tmp_path, monkeypatch):
    recipe = load_recipe(PENDULUM / "td3.toml", TINY)
    train(recipe, tmp_path / "runs" / "td3-s0", max_steps=400, progress=False, label="pendulum/td3")
    stopped = tmp_path / "runs" / "td3-s1"
    train_until_stopped(monkeypatch, load_recipe(PENDULUM / "td3.toml", [*TINY, "train.seed=1"]), stopped, 1,
                        max_steps=400, progress=False, label="pendulum/td3")
    last = (stopped / "metrics.csv").read_text().splitlines()[-1].split(",")  # phase, learn, step, return_mean ...
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(tmp_path / "runs"),
                           "--out", str(tmp_path / "finished"), "--no-extra-evals"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "(unfinished)" not in proc.stdout and str(stopped) not in proc.stdout
    assert (f"layered: note: 1 run in {tmp_path / 'runs'} not finished, left out (--unfinished reports such runs at "
            "their last evaluation)") in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(tmp_path / "runs"), "--unfinished",
                           "--out", str(tmp_path / "report")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "return: td3 | return: td3 (unfinished)" in proc.stdout and f"{float(last[3]):.1f} (1 seed)" in proc.stdout
    assert "evaluating" not in proc.stderr
    # the Runs table, its directories as followed from the report's
    assert f"| Pendulum-v1 | pendulum/td3 (unfinished) | 1 | ../runs/td3-s1 (phase 0, step {last[2]})" in proc.stdout


@pytest.mark.parametrize("seeds", [[], ["--seeds", "0,1"]], ids=["single", "group"])
def test_a_run_stopped_in_its_second_phase_reports_its_first_phase_results(seeds, tmp_path, monkeypatch):
    """A stopped run's finished phases are in phases.json, as its results.json will hold them: `report
    --unfinished` shows the first phase's best weights beside the second's last evaluation; once the run ends,
    results.json holds the same row and phases.json is gone."""
    out, steps = tmp_path / "runs" / "tla-c", 300
    run = out / "seed0" if seeds else out

    def stopped_at(step, command):  # the group stops after the second phase's `step`, a single run at an episode end
        stop_at(monkeypatch, [(1, step)])
        stop_at_episode_end(monkeypatch, 1 if command[0] == "resume" else 3)
        assert main(command) == 130
        monkeypatch.undo()

    stopped_at(50, ["train", str(PENDULUM / "tla-c.toml"), *seeds, "--steps", str(steps), *TINY, "--out", str(out)])
    first = json.loads((run / "phases.json").read_text())["phases"]
    assert [row["phase"] for row in first] == [0] and first[0]["learn"] == ["slow"]
    proc = subprocess.run([sys.executable, "-m", "layered.cli", "report", str(out), "--unfinished",
                           "--out", str(tmp_path / "report")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    per_seed = proc.stdout.split("## Per seed")[1]
    assert "| seed | phase 0 (slow): best | return |" in per_seed
    assert f"| {first[0]['fresh_best_return_mean']:.1f} |" in per_seed and "(phase 1, step " in proc.stdout
    (run / "phases.json").unlink()  # as a run started before the file was kept has none: a resume writes it
    stopped_at(100, ["resume", str(out)])
    assert json.loads((run / "phases.json").read_text())["phases"] == first
    assert main(["resume", str(out)]) == 0
    assert json.loads((run / "results.json").read_text())["phases"][0] == first[0]
    assert not (run / "phases.json").exists()


def test_report_of_nothing_is_a_clear_error(tmp_path):
    command = [sys.executable, "-m", "layered.cli", "report", str(tmp_path)]
    proc = subprocess.run(command, capture_output=True, text=True)
    assert proc.returncode == 2 and "no finished runs" in proc.stderr and "Traceback" not in proc.stderr


def test_real_time_runs_get_the_layout_of_table_3(tmp_path):
    from layered.report import write_report

    curve = [(0, 100.0), (5000, 3000.0)]
    setups = group([
        run("hopper/td3-realtime", 0, 3000.0, 0.4, curve, env="Hopper-v5", realtime=True),
        run("hopper/td3-realtime", 1, 3100.0, 0.5, curve, env="Hopper-v5", realtime=True),
        run("hopper/tla-realtime", 0, 3400.0, 0.6, curve, env="Hopper-v5", realtime=True),
        run("pendulum/td3", 0, -150.0, 0.8, [(0, -1000.0), (10, -150.0)]),
    ])
    text = write_report(setups, tmp_path)
    table3 = text.split("## Table 3")[1].split("##")[0]
    assert "| Hopper-v5 | 0.450 ± 0.050 | 0.600 (1 seed) | 3050.0 ± 50.0 | 3400.0 (1 seed) |" in table3
    assert "Pendulum-v1" not in table3 and "Pendulum-v1" in text.split("## Table 1")[1]
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_the_per_seed_table_shows_each_seed_and_its_earlier_phases(tmp_path):
    from layered.report import write_report

    def two_phases(seed, slow_best, final, best):
        slow = {"phase": 0, "learn": ["slow"], "fresh_best_return_mean": slow_best}
        last = {"phase": 1, "learn": ["fast"], "return_mean": final + 1.0, "auc": 0.25 * (seed + 1),
                "fresh_final_return_mean": final, "fresh_best_return_mean": best, "best_step": 5000 * seed,
                "fresh_best_repetition": 0.5}
        final = {k: v for k, v in last.items() if k != "learn"} | {"run_auc": 0.1 * (seed + 1)}  # (as read)
        return Run(Path(f"/r/tla-{seed}"), "Hopper-v5", "hopper/tla-realtime", seed, True, final, ((0, 1.0),),
                   phases=(slow, last))

    setups = group([two_phases(0, 900.0, 300.0, 400.0), two_phases(1, 500.0, 700.0, 1000.0)])
    text = write_report(setups, tmp_path)
    table = text.split("### Hopper-v5, hopper/tla-realtime")[1].split("##")[0]
    assert ("| seed | phase 0 (slow): best | return | AUC | AUC, whole run | final | best | best step | best AR "
            "| best AR at bounds |" in table)
    assert "| 0 | 900.0 | 301.0 | 0.250 | 0.100 | 300.0 | 400.0 | 0 | 50.0% | n/a |" in table  # (not measured)
    assert "| 1 | 500.0 | 701.0 | 0.500 | 0.200 | 700.0 | 1000.0 | 5000 | 50.0% | n/a |" in table
    assert ("| mean ± std | 700.0 ± 200.0 | 501.0 ± 200.0 | 0.375 ± 0.125 | 0.150 ± 0.050 | 500.0 ± 200.0 "
            "| 700.0 ± 300.0 | 2500 ± 2500 | 50.0% ± 0.0% |") in table
    # a setup of one phase: its AUC once
    one = group([replace(two_phases(0, 900.0, 300.0, 400.0), label="hopper/td3-realtime", phases=())])
    assert "| seed | return | AUC | final | best | best step | best AR |" in write_report(one, tmp_path / "one")
    rows = (tmp_path / "seeds.csv").read_text().splitlines()
    assert rows[0].startswith("env,label,method,seed,phase,learn,auc,best_step,")
    assert len(rows) == 5 and rows[1].startswith("Hopper-v5,hopper/tla-realtime,tla-realtime,0,0,slow,,,")
    assert rows[4].startswith("Hopper-v5,hopper/tla-realtime,tla-realtime,1,1,fast,0.5,5000,")


@pytest.mark.parametrize(("end", "values", "ticks"), [
    (800, (0, 200, 500, 800), ["0", "200", "500", "800"]),
    (2000, (0, 200, 500, 2000), ["0", "0.2k", "0.5k", "2k"]),
    (200_000, (0, 200, 125_000, 200_000), ["0", "0.2k", "125k", "200k"]),
    (1_000_000, (0, 125_000, 500_000, 1_000_000), ["0", "0.125M", "0.5M", "1M"]),
])
def test_step_axes_read_every_tick_in_the_unit_of_the_axis_end(end, values, ticks):
    """Ticks of one axis share a unit (0.5k ... 2k, not 500 ... 2k), that of the axis's end."""
    fig, ax = plt.subplots()
    _steps_axis(ax, "environment steps")
    ax.set_xlim(0, end)
    fmt = ax.xaxis.get_major_formatter()
    assert [fmt(v) for v in values] == ticks
    assert ax.get_xlabel() == "environment steps"
    plt.close(fig)


def test_the_repetitions_at_the_bounds_and_held_show_beside_the_repetition_and_as_n_a_in_older_results(tmp_path):
    from layered.report import results_table, write_report

    row = {"phase": 0, "learn": ["fast"], "active": ["fast"], "return_mean": -150.0, "return_std": 5.0, "auc": 0.9,
           "repetition": 0.5, "repetition_at_bounds": 0.125, "repetition_held": 0.25, "jerk": 0.25, "decisions": 200.0,
           "episode_steps": 200.0, "compute": 2e6}
    fresh = {"fresh_final_return_mean": -160.0, "fresh_final_return_std": 1.0, "fresh_final_repetition": 0.75,
             "fresh_final_repetition_at_bounds": 0.5, "fresh_final_repetition_held": 0.375, "best_step": 100,
             "best_return_mean": -140.0, "fresh_best_return_mean": -150.0, "fresh_best_return_std": 2.0,
             "fresh_best_repetition": 0.25, "fresh_best_repetition_at_bounds": 0.0, "fresh_best_repetition_held": 0.125}
    # results.json of earlier versions: before the repetition held, and before both measures
    before_held = {k: v for k, v in (row | fresh).items() if "held" not in k}
    before_both = {k: v for k, v in before_held.items() if "at_bounds" not in k}
    table = results_table([row | fresh, before_held, before_both]).splitlines()
    assert "| 0.900 | 50.0% | 12.5% | 25.0% | 0.250 |" in table[2]
    assert "| 0.900 | 50.0% | 12.5% | n/a | 0.250 |" in table[3] and "| 0.900 | 50.0% | n/a | n/a | 0.250 |" in table[4]
    assert "| 200.0 of 200 |" in table[2]
    assert "| 4.3 of 4.3 |" in results_table([row | {"decisions": 13 / 3, "episode_steps": 13 / 3}])  # never 4.3 of 4
    assert "| -160.0 ± 1.0 | 75.0% | 50.0% | 37.5% | 100 | -140.0 | -150.0 ± 2.0 | 25.0% | 0.0% | 12.5% |" in table[-3]
    assert "| -160.0 ± 1.0 | 75.0% | 50.0% | n/a | 100 | -140.0 | -150.0 ± 2.0 | 25.0% | 0.0% | n/a |" in table[-2]
    assert "| -160.0 ± 1.0 | 75.0% | n/a | n/a | 100 | -140.0 | -150.0 ± 2.0 | 25.0% | n/a | n/a |" in table[-1]
    del row["learn"], row["active"]  # (as a report reads a run's results)
    finals = [{**row, **fresh, "repetition_at_bounds": at, "repetition_held": kept} for at, kept in ((0.125, 0.5),
                                                                                                      (0.375, 0.25))]
    runs = [Run(Path(f"/r/td3-{seed}"), "Pendulum-v1", "pendulum/td3", seed, False, final, ((0, -150.0),))
            for seed, final in enumerate(finals)]
    text = write_report(group(runs), tmp_path)
    assert "| Pendulum-v1 | 50.0% ± 0.0% | 25.0% ± 12.5% | 37.5% ± 12.5% | 200.0 ± 0.0 |" in text.split("## Table 2")[1]


def test_a_sweep_of_the_default_grid_on_other_episodes_never_stands_in_for_fig_2(tmp_path):
    """`eval --threshold-sweep --episodes 1` on a run that evaluates on 2 keeps a name of its own, and a sweep of the
    default grid kept without its episodes (as `layered eval` wrote it before) is evaluated again for the report."""
    recipe = load_recipe(PENDULUM / "tla-c.toml", [*TINY, "eval.episodes=2"])
    train(recipe, tmp_path / "run", max_steps=200, progress=False)
    eval_dir = tmp_path / "run" / "eval"
    assert main(["eval", str(tmp_path / "run"), "--episodes", "1", "--threshold-sweep"]) == 0
    assert sorted(p.name for p in eval_dir.iterdir()) == ["threshold-sweep-episodes-1.csv",
                                                          "threshold-sweep-episodes-1.png"]
    assert "threshold sweep" in missing_figure_evals(tmp_path / "run")
    with (eval_dir / "threshold-sweep-episodes-1.csv").open() as f:  # as kept before episodes were recorded
        rows = [{k: v for k, v in row.items() if k != "episodes"} for row in csv.DictReader(f)]
    with (eval_dir / "threshold-sweep.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert "threshold sweep" in missing_figure_evals(tmp_path / "run")
    run_figure_evals(tmp_path / "run", ["threshold sweep"])
    with (eval_dir / "threshold-sweep.csv").open() as f:
        assert {row["episodes"] for row in csv.DictReader(f)} == {"2"}
    assert missing_figure_evals(tmp_path / "run") == ["gallery"]
