"""The `device` setting: CPU everywhere, CUDA where a GPU is present (those tests skip elsewhere)."""

import pytest
import torch
from conftest import assert_same_run, train_until_stopped

from layered import load_recipe
from layered.learners.td3 import resolve_device
from layered.recipe import RecipeError
from layered.trainer import build_learners, resume, train

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")


def test_auto_is_cuda_where_there_is_one_and_cpu_elsewhere():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_cuda_without_a_gpu_is_refused_by_the_recipe():
    with pytest.raises(RecipeError, match=r"learner\.device: .*no CUDA GPU"):
        load_recipe("recipes/pendulum/tla-c.toml", ["learner.device=cuda"])


@CUDA
@pytest.mark.parametrize("recipe", ["recipes/pendulum/tla-c.toml", "recipes/pendulum/temporl.toml",
                                    "recipes/pendulum/tla-joint.toml"])
def test_cuda_learners_keep_networks_and_buffers_on_the_gpu(recipe, tiny, tmp_path):
    loaded = load_recipe(recipe, [*tiny, "learner.device=cuda"])
    for learner in build_learners(loaded).values():
        td3 = getattr(learner, "td3", learner)
        assert next(td3.actor.parameters()).is_cuda and td3.buffer.device.type == "cuda"
    train(loaded, tmp_path, max_steps=300, progress=False)
    assert (tmp_path / "results.json").exists()


@CUDA
def test_cuda_run_resumes_to_the_same_files(tiny, tmp_path, monkeypatch):
    recipe = load_recipe("recipes/pendulum/tla-c.toml", [*tiny, "learner.device=cuda"])
    train(recipe, tmp_path / "whole", max_steps=400, progress=False)
    train_until_stopped(monkeypatch, recipe, tmp_path / "stopped", episodes=2, max_steps=400, progress=False)
    resume(tmp_path / "stopped", max_steps=400, progress=False)
    assert_same_run(tmp_path / "whole", tmp_path / "stopped")
