"""Recipes: validation names file and key, overrides reach every value, the resolved form reloads."""

from pathlib import Path

import pytest
import tomli_w
from conftest import layered_here

from layered import RecipeError, load_recipe
from layered.recipe import resolved

RECIPES = Path(__file__).parent.parent / "recipes"
TLA_C = RECIPES / "pendulum" / "tla-c.toml"


def errors(data, overrides=()):
    with pytest.raises(RecipeError) as e:
        load_recipe(data, overrides)
    return e.value.lines


def base(**kw):
    layers = [{"name": "slow", "period": 4}, {"name": "fast", "period": 1}]
    return {"env": {"id": "Pendulum-v1"}, "layers": layers, **kw}


def test_shipped_recipes_have_the_papers_settings():
    r = load_recipe(TLA_C)
    assert [(layer.name, layer.period) for layer in r.layers] == [("slow", 4), ("fast", 1)]
    assert r.train.order == "slow-to-fast" and r.train.steps_per_phase == 30000 and r.eval.every == 2500
    assert r.layers[1].sees == ["obs", "slow"] and r.combine.eval_threshold == 0.3
    o = load_recipe(RECIPES / "pendulum" / "tla-o.toml")
    assert o.combiner_kind(0) == "gate" and o.combiner_kind(1) is None and o.train.order == "fast-to-slow"
    assert len(load_recipe(RECIPES / "pendulum" / "td3.toml").layers) == 1


@pytest.mark.parametrize("folder", sorted(p for p in RECIPES.iterdir() if p.is_dir() and p.name != "research"),
                         ids=lambda p: p.name)
def test_the_recipes_of_one_task_are_evaluated_alike(folder):
    """A task's methods, baselines among them, are compared on one environment under one evaluation."""
    recipes = {p.name: load_recipe(p) for p in sorted(folder.glob("*.toml"))}
    assert len(recipes) >= 2, f"{folder.name}: a method without its baseline"
    settings = {name: (r.env.id, r.eval.every, r.eval.episodes, r.eval.fresh_episodes) for name, r in recipes.items()}
    assert len(set(settings.values())) == 1, settings


def test_td3_defaults_are_the_papers():
    c = load_recipe(base()).learner_config(0)
    assert (c.hidden, c.lr, c.batch_size, c.gamma, c.tau) == ((400, 300), 3e-4, 256, 0.99, 0.005)
    assert (c.policy_noise, c.noise_clip, c.exploration_noise, c.policy_delay) == (0.2, 0.5, 0.1, 2)
    assert load_recipe(base()).train.warmup == 1000


@pytest.mark.parametrize(
    ("change", "key", "says"),
    [
        ({"train": {"stepz": 3}}, "train.stepz", "unknown key"),
        ({"train": {"steps_per_phase": "many"}}, "train.steps_per_phase", "valid integer"),
        ({"train": {"steps_per_phase": -5}}, "train.steps_per_phase", "greater than 0"),
        ({"combine": {"kind": "blend"}}, "combine.kind", "unknown combiner 'blend'"),
        ({"train": {"order": "sideways"}}, "train.order", "unknown training order"),
        ({"env": {"id": "Pendulum-v9"}}, "env.id", "did you mean Pendulum-v1"),
        ({"learner": {"kind": "td3", "lr": "fast"}}, "learner.lr", "valid number"),
        ({"learner": {"kind": "ppo"}}, "learner.kind",
         "unknown learner 'ppo'; known: td3, td3-gate, temporl (one of your own: load its plugin with --plugin)"),
        ({"train": {"phases": [{"learn": ["medium"]}]}}, "train.phases[0].learn", "no layer named 'medium'"),
        ({"learner": {"kind": "td3", "compile": "cudagraphs"}}, "learner",
         "compile = 'cudagraphs' needs the learner on a GPU: device = 'cuda' or 'auto'"),
        ({"env": {"id": "Pendulum-v1", "return_range": [5, 1]}}, "env.return_range",
         "the worst return must be below the best, as [worst, best] (got [5.0, 1.0])"),
        ({"train": {"order": "fast-to-slow", "phases": [{"learn": ["slow"]}]}}, "train.phases",
         "the 'fast-to-slow' order makes its own phases and would ignore these"),
        ({"train": {"order": "explicit", "phases": [{"learn": ["fast"], "active": ["slow"]}]}},
         "train.phases[0].active", "leaves out 'fast', which learns in this phase: a layer learns where it is present"),
        ({"train": {"order": "explicit", "phases": [{"learn": ["fast"], "active": ["slow", "fast"]}]}}, "train.phases",
         "layer 'slow' is present in phase 0 but learns in no phase and starts from no layers[0].weights"),
    ],
)
def test_bad_values_are_one_line_naming_the_key(change, key, says):
    lines = errors(base(**change))
    assert len(lines) == 1
    assert lines[0].startswith(f"<recipe>: {key}: ") and says in lines[0]


def test_periods_must_divide_the_period_above():
    data = base()
    data["layers"][1]["period"] = 3
    (line,) = errors(data)
    assert "layers[1].period: period 3 does not divide the period 4 of layer 'slow'" in line


def test_a_layers_own_learner_table_is_checked_under_its_key():
    data = base()
    data["layers"][1]["learner"] = {"tau": 2.0}
    assert errors(data) == ["<recipe>: layers[1].learner.tau: input should be less than or equal to 1 (got 2.0)"]


def test_structure_errors():
    data = base()
    data["layers"][0]["sees"] = ["obs", "fast"]
    data["layers"][1]["name"] = "slow"
    data["layers"][1]["combine"] = "gate"
    lines = errors(data)
    assert any("layers[1].name: layer name 'slow' is used twice" in x for x in lines)
    assert any("layers[0].sees: 'fast' is neither 'obs' nor a slower layer" in x for x in lines)
    assert any("layers[1].combine: the fastest layer has no layer below" in x for x in lines)


def test_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[env]\nid = 'Pendulum-v1'\n[[layers]]\nname = 'a'\nperiod = 1\nwat = 2\n")
    assert errors(bad) == [f"{bad}: layers[0].wat: unknown key"]
    assert errors(tmp_path / "none.toml") == [f"{tmp_path / 'none.toml'}: no such recipe file"]
    assert errors("pendulm/tla-c") == ["pendulm/tla-c: no such recipe file; shipped recipes with a name like it: "
                                       "pendulum/tla-c, pendulum/tla-o, pendulum/tla-joint"]  # a shipped name mistyped
    assert errors("nothing/like-it") == ["nothing/like-it: no such recipe file"]
    assert errors("pendulum/tla-c.tom")[0].startswith("pendulum/tla-c.tom: no such recipe file; ")  # not tla-c.toml
    assert load_recipe("pendulum/tla-c").layers == load_recipe("pendulum/tla-c.toml").layers
    (tmp_path / "broken.toml").write_text("[env\n")
    assert "not valid TOML" in errors(tmp_path / "broken.toml")[0]


def test_overrides_by_dotted_key_layer_name_and_index():
    r = load_recipe(TLA_C, ["train.seed=7", "layers.fast.action_penalty=0.5", "layers[0].period=8",
                            "env.id=Pendulum-v1", "learner.lr=1e-3", "combine.per_dimension=true"])
    assert r.train.seed == 7 and r.layers[1].action_penalty == 0.5 and r.layers[0].period == 8
    assert r.learner["lr"] == 1e-3 and r.combine.per_dimension is True


def test_bad_overrides():
    assert "key=value" in errors(TLA_C, ["train.seed"])[0]
    assert "no entry named 'medium'" in errors(TLA_C, ["layers.medium.period=2"])[0]
    assert "out of range" in errors(TLA_C, ["layers.5.period=2"])[0]
    (line,) = errors(TLA_C, ["train.sed=1"])
    assert line == f"{TLA_C} (with command-line overrides): train.sed: unknown key"


def test_resolved_recipe_reloads_to_the_same_recipe(tmp_path):
    r = load_recipe(TLA_C, ["layers.fast.learner.lr=1e-3"])
    path = tmp_path / "recipe.toml"
    path.write_text(tomli_w.dumps(resolved(r)))
    again = load_recipe(path)
    assert resolved(again) == resolved(r)
    assert resolved(again)["layers"][1]["learner"]["lr"] == 1e-3


def test_cli_bad_recipe_exits_2_without_touching_the_output(tmp_path):
    out = tmp_path / "run"
    for args in (["layers.fast.period=3"], ["nonsense"], ["--steps", "0"]):
        proc = layered_here("train", TLA_C, *args, "--out", out)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr and proc.stderr.strip()
        assert not out.exists()


def test_response_times_in_seconds_become_periods_in_steps():
    data = base()
    data["layers"] = [{"name": "slow", "response_time": 0.2}, {"name": "fast", "response_time": 0.05, "period": 1}]
    r = load_recipe(data)  # Pendulum-v1 steps 0.05 s
    assert [layer.period for layer in r.layers] == [4, 1]
    data["layers"][0]["response_time"] = 0.07
    (line,) = errors(data)
    assert "layers[0].response_time: 0.07 s is not a whole number of the environment's 0.05 s steps" in line
    data["layers"][0] = {"name": "slow", "response_time": 0.2, "period": 2}
    assert "disagrees with response_time" in errors(data)[0]
    data["layers"][0] = {"name": "slow"}
    assert "give the layer a period" in errors(data)[0]


def test_response_time_needs_an_env_with_a_timestep():
    data = {"env": {"id": "MountainCarContinuous-v0"}, "layers": [{"name": "a", "response_time": 1.0}]}
    assert "defines no control timestep" in errors(data)[0]


def test_a_recipe_can_extend_another(tmp_path):
    (tmp_path / "child.toml").write_text(
        f'extends = "{TLA_C}"\n[env]\nid = "MountainCarContinuous-v0"\n[train]\nsteps_per_phase = 500\n'
    )
    r = load_recipe(tmp_path / "child.toml")
    parent = load_recipe(TLA_C)
    assert r.env.id == "MountainCarContinuous-v0" and r.train.steps_per_phase == 500
    assert r.layers == parent.layers and r.train.order == parent.train.order and r.eval == parent.eval


def test_extends_errors(tmp_path):
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    assert "extends itself" in errors(tmp_path / "a.toml")[0]
    (tmp_path / "c.toml").write_text('extends = "missing.toml"\n')
    missing = (tmp_path / "missing.toml").resolve()
    assert errors(tmp_path / "c.toml")[0] == f"{tmp_path / 'c.toml'}: extends: no such recipe file: {missing}"


def test_every_recipe_folder_python_could_import_is_a_package_of_the_wheel():
    # setuptools warns at every install about a data folder with an importable name that it is not told of
    import tomllib

    packages = tomllib.loads((RECIPES.parent / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    importable = {f"layered.recipes.{d.name}" for d in RECIPES.iterdir() if d.is_dir() and d.name.isidentifier()
                  and not d.name.startswith("_")}
    assert importable and importable <= set(packages)
