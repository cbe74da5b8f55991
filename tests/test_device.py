"""The `device` setting: CPU everywhere, CUDA where a GPU is present (those tests skip elsewhere)."""

import re
import pytest
import torch
from conftest import assert_same_run, train_until_stopped

from layered import load_recipe
from layered.learners.td3 import resolve_device
from layered.recipe import RecipeError
from layered.learner_set import build_learners
from layered.runs import resume, train

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")


def test_auto_is_cuda_where_there_is_one_and_cpu_elsewhere():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_cuda_without_a_gpu_is_refused_before_anything_is_written(tmp_path):
    recipe = load_recipe("pendulum/tla-c.toml", ["learner.device=cuda"])  # a recipe may name it
    with pytest.raises(RecipeError, match=r"learner\.device: .*no CUDA GPU"):
        train(recipe, tmp_path / "run", max_steps=100, progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("gpu_settings", [{}, {"compile": "cudagraphs"}, {"precision": "tf32"}])
def test_a_run_trained_for_a_gpu_evaluates_on_the_cpu(tmp_path, tiny, gpu_settings):
    """A run directory whose recipe names cuda (and settings only a GPU has) loads its learners on the CPU, here
    as on a laptop."""
    from layered.learner_set import load_learners

    recipe = load_recipe("pendulum/tla-c.toml", tiny)
    train(recipe, tmp_path, max_steps=200, progress=False)
    text = (tmp_path / "recipe.toml").read_text().replace('device = "cpu"', 'device = "cuda"')
    assert text.count('device = "cuda"') == 2  # each layer's learner table, as resolved
    for key, value in gpu_settings.items():
        text = re.sub(f'{key} = "[a-z0-9]+"', f'{key} = "{value}"', text)
        assert text.count(f'{key} = "{value}"') == 2
    (tmp_path / "recipe.toml").write_text(text)
    gpu_recipe = load_recipe(tmp_path / "recipe.toml")
    learners = load_learners(gpu_recipe, tmp_path)
    assert all(getattr(lr, "td3", lr).device.type == "cpu" for lr in learners.values())
    assert all(getattr(lr, "group", None) is None for lr in learners.values())  # acting as a plain TD3 there


@CUDA
@pytest.mark.parametrize("recipe", ["pendulum/tla-c.toml", "pendulum/temporl.toml",
                                    "pendulum/tla-joint.toml"])
def test_cuda_learners_keep_networks_and_buffers_on_the_gpu(recipe, tiny, tmp_path):
    loaded = load_recipe(recipe, [*tiny, "learner.device=cuda"])
    for learner in build_learners(loaded).values():
        td3 = getattr(learner, "td3", learner)
        assert next(td3.actor.parameters()).is_cuda and td3.buffer.device.type == "cuda"
    train(loaded, tmp_path, max_steps=300, progress=False)
    assert (tmp_path / "results.json").exists()


@CUDA
def test_cuda_run_resumes_to_the_same_files(tiny, tmp_path, monkeypatch):
    recipe = load_recipe("pendulum/tla-c.toml", [*tiny, "learner.device=cuda"])
    # one label for both: it defaults to the run directory's name, which results.json records
    train(recipe, tmp_path / "whole", max_steps=400, progress=False, label="x")
    train_until_stopped(monkeypatch, recipe, tmp_path / "stopped", episodes=2, max_steps=400, progress=False,
                        label="x")
    resume(tmp_path / "stopped", max_steps=400, progress=False)
    assert_same_run(tmp_path / "whole", tmp_path / "stopped")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
@pytest.mark.parametrize("setting", ["learner.compile=cudagraphs", "learner.precision=tf32"])
def test_gpu_settings_without_a_gpu_are_refused_before_anything_is_written(setting, tmp_path):
    recipe = load_recipe("pendulum/tla-c.toml", ["learner.device=auto", setting])
    key, value = setting.split("=")
    with pytest.raises(RecipeError, match=rf"{key}: '{value}' asked for, but .*no CUDA GPU"):
        train(recipe, tmp_path / "run", max_steps=100, progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("setting", ["learner.compile=cudagraphs", "learner.precision=tf32"])
def test_gpu_settings_on_a_cpu_learner_are_refused_as_the_recipe_loads(setting):
    with pytest.raises(RecipeError, match="a GPU"):
        load_recipe("pendulum/tla-c.toml", ["learner.device=cpu", setting])


@CUDA
@pytest.mark.parametrize("mode", ["inductor", "cudagraphs"])
def test_compiled_cuda_learners_train(mode, tiny, tmp_path):
    recipe = load_recipe("pendulum/tla-c.toml", [*tiny, "learner.device=cuda", f"learner.compile={mode}"])
    train(recipe, tmp_path, max_steps=300, progress=False)
    assert (tmp_path / "results.json").exists()


@CUDA
def test_tf32_updates_multiply_in_tf32_on_the_gpu_and_act_in_float32(tiny, tmp_path):
    """TF32 keeps 10 bits of a product's mantissa: a 256-wide float32 product is off by about 1e-3 of its size
    inside the updates' region (on a GPU from Ampere on), by about 1e-6 outside it, where acting runs; a run
    in tf32 trains (its group, captured as CUDA graphs, resumes exactly: tests/test_group_resume.py)."""
    from layered.learners.precision import update_region

    if torch.cuda.get_device_capability() < (8, 0):
        pytest.skip("TF32 needs an Ampere or later GPU")
    a, b = (torch.randn(256, 256, device="cuda", generator=torch.Generator("cuda").manual_seed(i)) for i in (0, 1))
    exact = a.double() @ b.double()

    def error() -> float:
        return float(((a @ b).double() - exact).abs().max() / exact.abs().max())

    outside = error()
    with update_region("tf32"):
        inside = error()
    assert outside < 1e-5 < 1e-4 < inside < 1e-2
    recipe = load_recipe("pendulum/tla-c.toml", [*tiny, "learner.device=cuda", "learner.precision=tf32"])
    train(recipe, tmp_path, max_steps=300, progress=False)
    assert (tmp_path / "results.json").exists()
    assert torch.get_float32_matmul_precision() == "highest"  # the process's own again, after every update
