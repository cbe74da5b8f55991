"""docs/extending.md shows the example plugins exactly, and each one works from a recipe."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import layered_here

DOCS = Path(__file__).parent.parent / "docs"
EXAMPLES = DOCS / "examples"
TINY = ["train.warmup=50", "eval.every=100", "eval.episodes=1", "eval.fresh_episodes=2"]
SMALL_TD3 = ["learner.hidden=[32, 32]", "learner.batch_size=32"]


def test_the_guide_shows_every_example_file_verbatim():
    guide = (DOCS / "extending.md").read_text()
    shown = dict(re.findall(r"<!-- file: (\S+) -->\n```\w+\n(.*?)```", guide, flags=re.S))
    assert set(shown) == {f"docs/examples/{p.name}" for p in EXAMPLES.iterdir() if p.suffix in (".py", ".toml")}
    for name, text in shown.items():
        assert text == (DOCS.parent / name).read_text(), f"{name} differs from the guide"


@pytest.mark.parametrize(("plugin", "recipe", "name", "small"), [
    ("deadband.py", "pendulum-deadband.toml", "residual-deadband", SMALL_TD3),
    ("centre.py", "pendulum-centre.toml", "centre", ["layers.fast.learner.hidden=[32, 32]"]),
    ("noisy.py", "pendulum-noisy.toml", "noisy", SMALL_TD3),
])
def test_each_example_plugin_trains_from_its_recipe_and_is_needed(plugin, recipe, name, small, tmp_path):
    def cli(*args):
        command = [sys.executable, "-m", "layered.cli", *map(str, args)]
        return subprocess.run(command, capture_output=True, text=True)

    out = tmp_path / "run"
    proc = cli("train", EXAMPLES / recipe, *TINY, *small, "--steps", 120, "--out", out, "--plugin", EXAMPLES / plugin)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "run.json").read_text())["plugins"] == [str((EXAMPLES / plugin).resolve())]
    assert cli("eval", out, "--episodes", 1).returncode == 0  # the run remembers its plugin
    report = cli("report", out, "--out", tmp_path / "report")  # (and the evaluations behind its figures find it)
    assert report.returncode == 0, report.stderr
    without = layered_here("train", EXAMPLES / recipe, "--out", tmp_path / "other")
    assert without.returncode == 2 and name in without.stderr


def test_a_missing_plugin_is_a_clear_error(tmp_path):
    proc = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", tmp_path / "nope.py")
    assert proc.returncode == 2 and "no such file" in proc.stderr and "Traceback" not in proc.stderr
    module = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", "nopackage.combiners")
    assert module.returncode == 2 and "No module named 'nopackage'" in module.stderr and "PYTHONPATH" in module.stderr


def test_the_deadband_combiner_drops_small_corrections_in_training_too():
    import numpy as np

    sys.path.insert(0, str(EXAMPLES))
    from layered.plugins import load_plugin

    load_plugin(str(EXAMPLES / "deadband.py"))
    from layered.combiners import COMBINERS

    combiner = COMBINERS.get("residual-deadband")()
    low, high = np.array([-2.0]), np.array([2.0])
    assert combiner.admit(np.array([1.0]), np.array([0.09]), low, high) == 0.0  # below 0.05 x 2
    assert combiner.admit(np.array([1.0]), np.array([0.11]), low, high) == pytest.approx(0.11)


def test_a_plugin_whose_entry_cannot_work_is_refused_in_one_line_before_anything_is_written(tmp_path):
    plugin = tmp_path / "narrow.py"
    plugin.write_text("from layered.combiners import COMBINERS, ResidualClip\n\n\n"
                      "@COMBINERS.register('narrow')\nclass Narrow(ResidualClip):\n"
                      "    def admit(self, contribution):\n        return contribution\n")
    proc = layered_here("train", EXAMPLES / "pendulum-deadband.toml", "--plugin", plugin, "combine.kind=narrow",
                        "--out", tmp_path / "run")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert "its admit(self, contribution) does not take what the library passes" in proc.stderr
    assert not (tmp_path / "run").exists()


def test_a_shared_learner_setting_one_layers_learner_lacks_is_refused_saying_where_it_came_from(tmp_path):
    proc = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", EXAMPLES / "centre.py",
                        "learner.hidden=[16, 16]", "--out", tmp_path / "run")
    assert proc.returncode == 2 and not (tmp_path / "run").exists()
    assert "layers[0].learner.hidden: unknown key (layer 'slow' takes it from [learner]" in proc.stderr
    assert "layers.<name>.learner.hidden" in proc.stderr
    proc = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", EXAMPLES / "centre.py",
                        "layers.slow.learner.hidden=[16, 16]", "--out", tmp_path / "run")
    assert proc.returncode == 2 and "layers[0].learner.hidden: unknown key" in proc.stderr
    assert "[learner]" not in proc.stderr  # the layer's own table said it


FLAWED_LEARNERS = '''
import numpy as np
import torch

from layered.learners import LEARNERS, LearnerConfig


class Flawed(LEARNERS.get("centre")):  # (docs/examples/centre.py, loaded first)
    loss_names = ("x",)

    def state_dict(self):
        return {"w": torch.zeros(2)}

    def load_state_dict(self, state):
        state["w"]


def register(name, **methods):
    config = type(f"{name}Config", (LearnerConfig,), {"__annotations__": {"kind": str}, "kind": name})
    LEARNERS.register(name)(type(name, (Flawed,), {"Config": config, **methods}))


register("flawed-numpy", state_dict=lambda self: {"w": np.zeros(2)})
register("flawed-keys", load_state_dict=lambda self, state: state["missing"])
register("flawed-loss", update=lambda self: {"x": 1.0})
'''


@pytest.mark.parametrize(("kind", "says", "written"), [
    ("flawed-numpy", "its state_dict() holds a numpy.ndarray at ['w']; a checkpoint holds tensors", False),
    ("flawed-keys", "load_state_dict() cannot take what state_dict() returns (KeyError: 'missing')", False),
    ("flawed-loss", "its update returned 'x' as a float; it returns 0-d tensors named in its loss_names", True),
])
def test_a_plugin_learner_that_a_run_could_not_save_resume_or_log_is_refused_in_one_line(kind, says, written,
                                                                                           tmp_path):
    plugin = tmp_path / "flawed.py"
    plugin.write_text(FLAWED_LEARNERS)
    proc = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", EXAMPLES / "centre.py",
                        "--plugin", plugin, *TINY, f"layers.slow.learner.kind={kind}",
                        "layers.fast.learner.hidden=[32, 32]", "--steps", 300, "--out", tmp_path / "run")
    errors = [line for line in proc.stderr.splitlines() if line.startswith("layered: error")]
    assert proc.returncode == 2 and len(errors) == 1, proc.stderr
    assert errors[0].startswith(f"layered: error: learner {kind!r} (layer 'slow'): ") and says in errors[0]
    assert (tmp_path / "run").exists() == written  # (refused before the run starts where it can be)


def test_device_is_set_on_the_layers_whose_learner_has_one(tmp_path):
    from layered.plugins import load_plugin
    from layered.sweep import plan

    load_plugin(str(EXAMPLES / "centre.py"))
    jobs = plan([EXAMPLES / "pendulum-centre.toml"], 1, tmp_path / "sweep", device="cuda")  # (planned, not run)
    layers = jobs[0].recipe["layers"]
    assert "device" not in layers[0]["learner"] and layers[1]["learner"]["device"] == "cuda"
    proc = layered_here("train", EXAMPLES / "pendulum-centre.toml", "--plugin", EXAMPLES / "centre.py",
                        "--device", "cpu", "layers.fast.learner.kind=centre", "--out", tmp_path / "run")
    assert proc.returncode == 2 and "--device cpu: no layer's learner has a device setting" in proc.stderr


def test_a_run_whose_plugin_file_has_moved_is_given_its_new_place_with_plugin(tmp_path):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "layered.cli", *map(str, args)], capture_output=True, text=True)

    (tmp_path / "before").mkdir()
    plugin = tmp_path / "before" / "deadband.py"
    plugin.write_text((EXAMPLES / "deadband.py").read_text())
    out = tmp_path / "run"
    assert cli("train", EXAMPLES / "pendulum-deadband.toml", *TINY, *SMALL_TD3, "--steps", 100, "--out", out,
               "--plugin", plugin).returncode == 0
    moved = plugin.rename(tmp_path / "deadband.py")
    lost = cli("eval", out, "--episodes", 1)
    assert lost.returncode == 2 and "give its new place with --plugin" in lost.stderr
    found = cli("eval", out, "--episodes", 1, "--plugin", moved)
    assert found.returncode == 0 and "is no longer there; using" in found.stderr
