"""The updates' precision: what `auto` resolves to, the actor's squashing kept in float32, the TF32 region
and its refusal off a GPU, and a resumed learner keeping the precision it was trained in."""

import json

import numpy as np
import pytest
import torch
from gymnasium.spaces import Box

from layered.buffer import Transition

from layered.learners import precision
from layered.learners.precision import autocast, cpu_flags, resolve_precision, update_region
from layered.learners.td3 import TD3, TD3Config, squash
from layered.learners.td3_group import TD3Group
from layered.outputs import OutputLayout

OBS = Box(-1.0, 1.0, (3,), np.float32)
ACT = Box(-1.0, 1.0, (2,), np.float32)
CPU = torch.device("cpu")


def test_cpu_flags_are_read_from_x86_and_arm_cpuinfo(tmp_path):
    x86, arm = tmp_path / "x86", tmp_path / "arm"
    x86.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx512f avx512_bf16\n\n"
                   "processor\t: 1\nflags\t\t: fpu amx_bf16\n")
    arm.write_text("processor\t: 0\nFeatures\t: fp asimd bf16 i8mm\nCPU implementer\t: 0x41\n")
    assert cpu_flags(x86) == {"fpu", "sse2", "avx512f", "avx512_bf16", "amx_bf16"}
    assert cpu_flags(arm) == {"fp", "asimd", "bf16", "i8mm"}
    assert cpu_flags(tmp_path / "absent") == frozenset()


@pytest.mark.parametrize("flags, resolved", [({"avx512f", "avx512_bf16"}, "bfloat16"), ({"amx_bf16"}, "bfloat16"),
                                             ({"bf16"}, "bfloat16"), ({"avx512f", "avx2"}, "float32"),
                                             (set(), "float32")])
def test_auto_is_bfloat16_on_cpus_that_multiply_it_in_hardware(monkeypatch, flags, resolved):
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset(flags))
    assert resolve_precision("auto", CPU) == resolved
    assert resolve_precision("float32", CPU) == "float32" and resolve_precision("bfloat16", CPU) == "bfloat16"


@pytest.mark.parametrize("native", [True, False])
def test_auto_on_a_gpu_asks_for_native_bfloat16(monkeypatch, native):
    asked = []
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation: asked.append(including_emulation)
                        or native)
    assert resolve_precision("auto", torch.device("cuda")) == ("bfloat16" if native else "float32")
    assert asked == [False]


def test_tf32_is_a_gpu_precision():
    assert resolve_precision("tf32", torch.device("cuda")) == "tf32"
    with pytest.raises(ValueError, match="'tf32' needs the learner on a GPU"):
        resolve_precision("tf32", CPU)
    with pytest.raises(ValueError, match="'tf32' is a GPU's"):
        TD3Config(precision="tf32", device="cpu")
    assert TD3Config(precision="tf32", device="auto").precision == "tf32"  # refused at the recipe's check without one


def test_the_tf32_region_sets_torchs_float32_products_to_tf32_and_gives_back_the_processs_own():
    """Inside it, torch's float32 matmul precision is "high" (TF32 on a GPU); after it, even after an error,
    whatever the process had, so that acting and the user's own code stay as they were."""
    before = torch.get_float32_matmul_precision()
    try:
        for own in ("highest", "medium"):
            torch.set_float32_matmul_precision(own)
            with update_region("tf32"):
                assert torch.get_float32_matmul_precision() == "high"
            assert torch.get_float32_matmul_precision() == own
            with pytest.raises(RuntimeError, match="inside"), update_region("tf32"):
                raise RuntimeError("inside")
            assert torch.get_float32_matmul_precision() == own
            with update_region("float32"), update_region("bfloat16"), autocast("tf32", CPU):  # the others leave it
                assert torch.get_float32_matmul_precision() == own and not torch.is_autocast_enabled("cpu")
    finally:
        torch.set_float32_matmul_precision(before)


def test_a_tf32_learners_update_runs_inside_the_region_and_leaves_it(monkeypatch):
    """A single learner's and a group's whole update runs in TF32's region (outside their steps, which torch
    may compile or capture and which cannot change torch's settings themselves), and acting after it."""
    config = TD3Config(hidden=(8,), batch_size=4, precision="float32")
    single = TD3(OBS, ACT, OutputLayout(2), config, 0)
    group = TD3Group([TD3(OBS, ACT, OutputLayout(2), config, s) for s in (0, 1)])
    obs, action = np.zeros((2, 3), np.float32), np.zeros((2, 2), np.float32)
    for _ in range(8):
        single.observe(Transition(obs[0], action[0], 1.0, obs[0], False, 0.99))
        group.observe(obs, action, np.ones(2), obs, np.zeros(2, bool), np.full(2, 0.99))
    seen = []
    for learner, step in ((single, "_critic_step"), (group, "critic_step")):
        learner.precision = "tf32"  # as a GPU's learner (refused on a CPU; here torch's setting has no effect)
        inner = getattr(learner, step)
        monkeypatch.setattr(learner, step, lambda *a, inner=inner: seen.append(torch.get_float32_matmul_precision())
                            or inner(*a))
    own = torch.get_float32_matmul_precision()
    single.update(), group.update()
    assert seen == ["high", "high"] and torch.get_float32_matmul_precision() == own  # own again, for acting


def test_the_actors_squashing_keeps_a_gradient_where_bfloat16_rounds_tanh_to_one():
    """tanh(4) = 0.99933 is 1.0 in bfloat16, where tanh's gradient 1 - tanh² is zero; in float32 it is
    1 - 0.99933² = 0.0013409 (passed back through the bfloat16 product: within bfloat16's 1/256)."""
    x = torch.tensor([[4.0, -4.0]], requires_grad=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = squash(torch.nn.functional.linear(x, torch.eye(2)))
        rounded = torch.tanh(torch.nn.functional.linear(x, torch.eye(2)))
    assert y.dtype == torch.float32 and rounded.dtype == torch.bfloat16
    assert rounded.abs().tolist() == [[1.0, 1.0]]
    y.sum().backward()
    assert x.grad[0].tolist() == pytest.approx([0.0013409, 0.0013409], rel=1 / 256)


def test_a_learner_loaded_from_a_checkpoint_keeps_the_precision_auto_chose_where_it_was_trained(monkeypatch):
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx512_bf16"}))
    trained = TD3(OBS, ACT, OutputLayout(2), TD3Config(hidden=(8,)), 0)
    assert trained.precision == "bfloat16" and trained.state_dict()["precision"] == "bfloat16"
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset())
    elsewhere = TD3(OBS, ACT, OutputLayout(2), TD3Config(hidden=(8,)), 0)
    assert elsewhere.precision == "float32"
    elsewhere.load_state_dict(trained.state_dict())
    assert elsewhere.precision == "bfloat16"
    chosen = TD3(OBS, ACT, OutputLayout(2), TD3Config(hidden=(8,), precision="float32"), 0)
    chosen.load_state_dict(trained.state_dict())
    assert chosen.precision == "float32"  # a precision the recipe names is the one used
    older = {k: v for k, v in trained.state_dict().items() if k != "precision"}
    elsewhere = TD3(OBS, ACT, OutputLayout(2), TD3Config(hidden=(8,)), 0)
    elsewhere.load_state_dict(older)
    assert elsewhere.precision == "float32"


def test_a_group_keeps_its_precision_across_a_resume_and_gives_it_to_its_seeds(monkeypatch):
    def group():
        return TD3Group([TD3(OBS, ACT, OutputLayout(2), TD3Config(hidden=(8,)), s) for s in (0, 1)])

    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"amx_bf16"}))
    trained = group()
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset())
    resumed = group()
    assert (trained.precision, resumed.precision) == ("bfloat16", "float32")
    resumed.load_resume_state(trained.resume_state())
    assert resumed.precision == "bfloat16" and resumed.seed_state_dict(1)["precision"] == "bfloat16"


def test_a_run_records_what_auto_computed_in_and_the_report_tells_the_machines_runs_apart(monkeypatch, tmp_path, tiny):
    from pathlib import Path

    from layered.group import group_recipes, train_group
    from layered.recipe import load_recipe
    from layered.runs import train
    from layered.summary import find_runs, group

    recipe = Path(__file__).parent.parent / "recipes" / "pendulum" / "tla-c.toml"
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx512_bf16"}))
    train(load_recipe(recipe, tiny), tmp_path / "bf16", max_steps=150, progress=False, label="p/tla-c")
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx2"}))
    recipes = group_recipes(recipe, [1, 2], tiny)
    train_group(recipes, [tmp_path / "group" / f"seed{k}" for k in (1, 2)], "p/tla-c", max_steps=150, progress=False)
    # one named in the recipe is recorded as set
    train(load_recipe(recipe, [*tiny, "layers.fast.learner.precision=bfloat16"]), tmp_path / "set", max_steps=150,
          progress=False, label="p/tla-c")
    recorded = {run: json.loads((tmp_path / run / "run.json").read_text())["precision"]
                for run in ("bf16", "group/seed1", "group/seed2", "set")}
    assert recorded == {"bf16": {"slow": "bfloat16", "fast": "bfloat16"},
                        "group/seed1": {"slow": "float32", "fast": "float32"},
                        "group/seed2": {"slow": "float32", "fast": "float32"},
                        "set": {"slow": "float32", "fast": "bfloat16"}}
    setups = group(find_runs([tmp_path]))
    assert sorted((s.label, sorted(r.seed for r in s.runs)) for s in setups) == [
        ("p/tla-c layers.fast.learner.precision=bfloat16 layers.slow.learner.precision=bfloat16 trained=alone", [0]),
        ("p/tla-c layers.fast.learner.precision=bfloat16 layers.slow.learner.precision=float32 trained=alone", [0]),
        ("p/tla-c layers.fast.learner.precision=float32 layers.slow.learner.precision=float32 trained=group",
         [1, 2])]
