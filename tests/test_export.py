"""`layered export`: an exported stack, run by the standalone runtime, executes the same actions as
the library on real episodes (periods, holds, delays, thresholds, gates and repeats), plugin
combiners included."""

import json
import subprocess
import sys

import numpy as np
import pytest

from layered import load_recipe
from layered.cli import main
from layered.export import export_stack
from layered.latency import compare
from layered.learner_set import build_learners
from layered.orders import phases_of
from layered.runtime import load_stack

SMALL = ["learner.hidden=[32, 32]"]
STACKS = {
    "2 layers, residual-clip with a threshold": ("pendulum/tla-c.toml", []),
    "3 layers, residual-clip": ("research/pendulum-residual-3.toml", []),
    "3 layers, gate over residual": ("research/pendulum-gate-over-residual-3.toml", []),
    "jointly gated (td3-gate learner)": ("pendulum/tla-joint.toml", []),
    "repeats (TempoRL)": ("pendulum/temporl.toml", []),
    "real-time delays, MuJoCo": ("inverted-double-pendulum/tla-realtime.toml", []),
    "real-time delays, without what acts beside the output in flight": ("inverted-double-pendulum/tla-realtime.toml",
                                                                         ["layers.fast.sees_in_flight=false"]),
    "real-time delays, outputs in flight seen as executed": ("inverted-double-pendulum/tla-realtime.toml",
                                                             ["layers.slow.sees_executed=true"]),
    "per-dimension threshold, MuJoCo": ("hopper/tla-realtime.toml", ["combine.per_dimension=true"]),
}


def exported(path, overrides, tmp_path, backend="torchscript"):
    recipe = load_recipe(path, SMALL + overrides)
    learners = build_learners(recipe)  # untrained: the stack's rules, not the policies, are under test
    active = list(phases_of(recipe)[-1].active)
    return recipe, learners, active, export_stack(recipe, learners, active, tmp_path / backend, backend)


@pytest.mark.parametrize("name", list(STACKS))
def test_exported_stack_executes_the_library_actions(name, tmp_path):
    recipe, learners, active, out = exported(*STACKS[name], tmp_path)
    result = compare(recipe, learners, active, out, episodes=4, seed=7)
    assert result.steps >= 30  # untrained, the double pendulum falls within about 8 steps
    assert result.max_difference == 0.0


def test_onnx_export_executes_the_library_actions(tmp_path):
    recipe, learners, active, out = exported("research/pendulum-gate-over-residual-3.toml", [], tmp_path,
                                             "onnx")
    assert sorted(p.name for p in out.iterdir()) == [
        "fast.onnx", "layered_runtime", "mid.onnx", "slow.onnx", "stack.json"]
    result = compare(recipe, learners, active, out, episodes=2, seed=7)
    assert result.matches and result.max_difference < 1e-5
    assert result.exported_return == pytest.approx(result.library_return, rel=1e-3)


def test_the_runtime_carries_the_librarys_own_rules_and_they_import_nothing_of_it(tmp_path):
    """One implementation of the rules: the exported package holds the library's modules byte for byte,
    and those import numpy, the standard library and each other (relatively) only; the runtime also the
    policies' backend when it loads them."""
    import ast
    import inspect

    from layered.export import RUNTIME_MODULES

    *_, out = exported("pendulum/tla-c.toml", [], tmp_path)
    allowed = set(sys.stdlib_module_names) | {"numpy", "torch", "onnxruntime"}
    for file, module in RUNTIME_MODULES.items():
        source = inspect.getsource(module)
        assert (out / "layered_runtime" / file).read_text() == source, file
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ImportFrom) and node.level == 0:
                assert node.module.split(".")[0] in allowed, f"{file} imports {node.module}"
            elif isinstance(node, ast.Import):
                assert {a.name.split(".")[0] for a in node.names} <= allowed, f"{file} imports {ast.unparse(node)}"


def test_exported_directory_runs_with_torch_alone(tmp_path):
    """The runtime imports nothing of layered: a fresh interpreter without it on the path runs it."""
    *_, out = exported("pendulum/tla-c.toml", [], tmp_path)
    script = ("import sys; sys.path.insert(0, '.'); sys.modules['layered'] = None; "
              "from layered_runtime import load_stack; import numpy as np; s = load_stack('.'); s.reset(); "
              "print([round(float(s.step(np.ones(3, np.float32))[0]), 6) for _ in range(6)], s.decided)")
    done = subprocess.run([sys.executable, "-I", "-c", script], cwd=out, capture_output=True, text=True, check=True)
    assert done.stdout.strip().endswith("['fast']")  # step 5: period 4 slow layer idle, the fast one decides


def test_the_runtime_refuses_an_observation_of_another_size_and_a_format_not_exported_in_one_line(tmp_path):
    *_, out = exported("pendulum/tla-c.toml", [], tmp_path)
    stack = load_stack(out)
    stack.reset()
    with pytest.raises(ValueError, match=r"observations of 3 numbers \(those of Pendulum-v1, flattened\), got 4"):
        stack.step(np.ones(4, np.float32))
    with pytest.raises(FileNotFoundError, match=r"no onnx policy .*slow\.onnx: export the run with --format onnx"):
        load_stack(out, backend="onnx")


HALVING = """
import numpy as np

from layered.combiners import COMBINERS, Combiner, Route


@COMBINERS.register("test-halving")
class Halving(Combiner):
    \"\"\"The layers below add half of their action; at evaluation a half below the threshold is dropped.\"\"\"

    thresholded = True

    def route(self, output):
        return np.full(np.shape(output)[:-1], Route.ADD, np.int8)

    def admit(self, above, contribution, low, high):
        half = contribution / 2
        if self.threshold is None:
            return half
        return np.where(np.abs(half) < self.threshold, 0.0, half).astype(contribution.dtype)
"""


def test_a_plugin_combiner_trains_evaluates_draws_its_threshold_figure_and_exports(tmp_path, tiny):
    plugin, run = tmp_path / "halving.py", tmp_path / "run"
    plugin.write_text(HALVING)

    def cli(*args):
        done = subprocess.run([sys.executable, "-m", "layered.cli", *map(str, args)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout

    cli("train", "pendulum/tla-c.toml", "combine.kind=test-halving", *tiny, "--steps", 300, "--out", run,
        "--plugin", plugin)
    cli("eval", run, "--threshold-sweep", "0,0.5", "--episodes", 1)
    assert (run / "eval" / "threshold-sweep-0-0.5.png").exists()
    printed = cli("export", run, "--episodes", 1)
    assert "the same executed actions" in printed
    out = run / "export-torchscript"
    assert (out / "plugins" / "halving.py").read_text() == HALVING
    script = ("import sys; sys.path.insert(0, '.'); sys.modules['layered'] = None; "
              "from layered_runtime import load_stack; import numpy as np; s = load_stack('.'); s.reset(); "
              "print(type(s.rules.layers[0].combiner).__name__, [s.step(np.ones(3, np.float32)) for _ in range(3)])")
    done = subprocess.run([sys.executable, "-I", "-c", script], cwd=out, capture_output=True, text=True, check=True)
    assert done.stdout.startswith("Halving")


def test_export_command_on_a_trained_run(tmp_path, tiny, capsys):
    run = tmp_path / "run"
    assert main(["train", "pendulum/tla-c.toml", "--out", str(run), "--steps", "300", *tiny]) == 0
    capsys.readouterr()
    assert main(["export", str(run), "--episodes", "1"]) == 0
    printed = capsys.readouterr().out
    assert "the same executed actions (largest difference 0," in printed
    check = json.loads((run / "export-torchscript" / "check.json").read_text())
    assert check["steps"] == 200 and check["exported"]["median_us"] > 0 and check["matches"]
    assert check["exported_return"] == check["library_return"]
    assert (check["run"], check["weights"], check["threshold"]) == (str(run.resolve()), "best", None)
    assert np.isfinite(check["library"]["p99_us"])
    assert main(["eval", str(run), "--episodes", "1"]) == 0  # the same episode, its products batched as an eval's
    evaluated = json.loads((run / "eval" / "threshold-recipe-episodes-1.json").read_text())
    assert check["library_return"] == pytest.approx(evaluated["return_mean"], rel=1e-5)


def test_an_export_cut_short_says_its_files_are_unchecked_and_leaves_no_earlier_check(tmp_path, tiny, monkeypatch,
                                                                                        capsys):
    """A Ctrl-C between writing the files and checking them (or a check that fails) leaves an export without a
    check.json, and says so; an earlier export's check.json is gone once the files it checked are replaced."""
    import layered.latency

    run = tmp_path / "run"
    assert main(["train", "pendulum/tla-c.toml", "--out", str(run), "--steps", "150", *tiny]) == 0
    assert main(["export", str(run), "--episodes", "1"]) == 0 and (run / "export-torchscript" / "check.json").exists()
    capsys.readouterr()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(layered.latency, "compare", interrupted)
    assert main(["export", str(run), "--episodes", "1"]) == 130
    said = capsys.readouterr().err
    assert f"{run / 'export-torchscript'} may hold an export that was not checked (it has no check.json)" in said
    export = run / "export-torchscript"
    assert (export / "stack.json").exists() and not (export / "check.json").exists()
