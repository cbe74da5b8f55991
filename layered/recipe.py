"""Recipes: TOML files over typed schemas, validated on load with errors that name file and key."""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from layered.combiners import COMBINERS
from layered.envs import env_info, env_spaces
from layered.learners import LEARNERS, LearnerConfig
from layered.orders import MAKE_OWN_PHASES, ORDERS
from layered.stack import output_layout, reward_per_step


class RecipeError(ValueError):
    """A recipe that cannot be used; each line names the source, the key and what was expected."""

    def __init__(self, source: str, problems: list[tuple[str, str]]) -> None:
        self.lines = [f"{source}: {key or '(top level)'}: {message}" for key, message in problems]
        super().__init__("\n".join(self.lines))


class Section(BaseModel):
    """Base of every recipe table: frozen, unknown keys are errors, attribute docstrings documented."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)


class EnvConfig(Section):
    """The environment every layer controls."""

    id: str
    """Environment id, `family:name`; a bare name is a Gymnasium id, e.g. `Pendulum-v1`."""
    return_range: tuple[float, float] | None = None
    """(worst, best) return that normalises the AUC; defaults to the environment registry's."""

    @field_validator("return_range")
    @classmethod
    def _worst_below_best(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        if value is not None and not value[0] < value[1]:
            raise ValueError(f"the worst return must be below the best, as [worst, best] (got {list(value)})")
        return value


class CombineConfig(Section):
    """The default combiner of every layer, and its evaluation threshold."""

    kind: str = "residual-clip"
    """Combiner name: `residual-clip` or `gate` (or any registered one)."""
    eval_threshold: float = Field(default=0.3, ge=0)
    """At evaluation, lower residual contributions whose effect is below this fraction of the
    maximum action are zeroed; 0 disables thresholding."""
    per_dimension: bool = False
    """Threshold each action dimension on its own instead of all dimensions together."""


class LayerConfig(Section):
    """One controller of the stack; layers are listed slowest first."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_-]*$")
    """Unique name, used in `sees`, in phases and as the agent's name."""
    period: int | None = Field(default=None, gt=0)
    """Base environment steps between decisions; must divide the period of the layer above."""
    response_time: float | None = Field(default=None, gt=0)
    """The period in seconds instead of steps; must be a whole number of the env's control timestep."""
    delay: int = Field(default=0, ge=0)
    """Decisions between choosing an action and its taking effect (1: the real-time setting)."""
    max_repeat: int = Field(default=1, ge=1)
    """Above 1 the layer also chooses for how many of its periods (1..max_repeat) to hold its
    output before deciding again, as TempoRL's skip policy; its output gains that count."""
    sees: list[str] = ["obs"]
    """What the layer observes: `obs` and the names of slower layers whose held actions it sees."""
    combine: str | None = None
    """How this layer merges with the layers below; defaults to `combine.kind`."""
    eval_threshold: float | None = Field(default=None, ge=0)
    """Overrides `combine.eval_threshold` for the layers below this one."""
    action_scale: float = Field(default=1.0, gt=0)
    """The layer's action range as a multiple of the environment's (2 lets a residual cancel)."""
    action_penalty: float = Field(default=0.0, ge=0)
    """Reward penalty per step: this times the mean of |action| / the layer's action bound."""
    action_penalty_unit: Literal["reward", "reward-per-step"] = "reward"
    """`reward`: the penalty is in the environment's reward (the paper's); `reward-per-step`: in
    units of its return range per step ((best - worst return) / episode steps), so one value
    weighs the same against tasks of other reward scales."""
    defer_reward_scale: tuple[float, float] = (2.0, 0.5)
    """Gate layers: factors on rewards r <= 0 and r > 0 earned while the layers below act."""
    defer_penalty: float = Field(default=0.0, ge=0)
    """Gate layers: reward penalty per base step while the layers below act (p per step)."""
    deviation_penalty: float = Field(default=0.0, ge=0)
    """Reward penalty per step: this times mean |executed action - action proposed by the
    nearest deferring gate at or above this layer| / max action (j)."""
    warmup: int | None = Field(default=None, ge=0)
    """Decisions this layer takes uniformly at random before it learns; default `train.warmup`."""
    updates: int = Field(default=1, gt=0)
    """Gradient updates of the layer's learner after each of its decisions once it learns; with
    `updates = period`, one per base step, as the authors' jointly trained slow layer and gate make."""
    learn_from_commits: bool = False
    """For the layer right below a gate: in training, while the gate commits, the layer still
    decides at its period, and the executed action is recorded as its decision, so that it learns
    from every step, as the authors' jointly trained fast layer does (otherwise it learns only
    from the steps it acts on). Evaluation never asks it while the gate commits."""
    weights: str | None = None
    """A checkpoint the layer starts from instead of new networks: another run's
    `checkpoints/<name>.best.pt` or `<name>.pt` (a path relative to the recipe file that sets it).
    The run keeps a copy, so a layer that only acts here needs no phase of its own."""
    learner: dict[str, Any] = {}
    """Learner settings for this layer, over the recipe's `[learner]` table."""


class PhaseConfig(Section):
    """One training phase of an explicit order."""

    learn: list[str] = Field(min_length=1)
    """Layers that learn in this phase."""
    active: list[str] | None = None
    """Layers present in this phase; default: `learn` plus every layer trained before."""
    steps: int | None = Field(default=None, gt=0)
    """Base environment steps of this phase; default `train.steps_per_phase`."""


class TrainConfig(Section):
    """How the stack is trained."""

    order: str = "slow-to-fast"
    """Training order: `slow-to-fast`, `fast-to-slow`, `joint` (every layer learns at once, in one
    phase), or `explicit` (with `phases`); or any registered one."""
    phases: list[PhaseConfig] | None = None
    """Explicit phases; giving them selects the `explicit` order."""
    steps_per_phase: int = Field(default=30_000, gt=0)
    """Base environment steps per phase."""
    checkpoint_every: int | None = Field(default=None, gt=0)
    """Environment steps between checkpoints of the whole training state, each taken at the next
    episode end; default `eval.every`. A stopped run resumes from its last checkpoint."""
    select: Literal["final", "best"] = "final"
    """Which weights of a finished phase's learning layers later phases and `layered eval` use:
    those at the phase's end (`final`) or at its best evaluation (`best`, the paper authors'
    protocol). Both are saved, and both are evaluated again on fresh episodes (eval.fresh_episodes)."""
    warmup: int = Field(default=1000, ge=0)
    """Decisions of each learning layer taken uniformly at random before updates start (a
    layer's own `warmup` overrides it)."""
    discount: Literal["decision", "step"] = "decision"
    """`decision`: gamma per decision of a layer; `step`: gamma**k for a decision spanning k steps."""
    seed: int = Field(default=0, ge=0)
    """Seed of the environment, the networks and the exploration."""

    @model_validator(mode="before")
    @classmethod
    def _phases_select_explicit(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("phases") is not None and "order" not in data:
            return {**data, "order": "explicit"}
        return data


class EvalConfig(Section):
    """How the stack is evaluated during and after training."""

    every: int = Field(default=5000, gt=0)
    """Base environment steps between evaluations within a phase."""
    episodes: int = Field(default=10, gt=0)
    """Deterministic episodes per evaluation."""
    seed_offset: int = 100
    """The evaluation environment is seeded with train.seed plus this offset."""
    fresh_episodes: int = Field(default=100, ge=0)
    """At the end of each phase its final and its best weights are each evaluated on this many
    fresh episodes: the best of several evaluations overestimates, these do not. 0 skips it."""
    fresh_seed_offset: int = 1000
    """The fresh episodes' environment is seeded with train.seed plus this offset."""


class LogConfig(Section):
    """What a run writes besides its CSV logs and results."""

    tensorboard: bool = False
    """Also write TensorBoard event files (run directory's `tensorboard/`, one run per phase): every
    row of metrics.csv as scalars. Needs the extra `layered[tensorboard]`."""


class Recipe(Section):
    """A whole experiment: environment, layer stack, combiners, learners, training and evaluation."""

    env: EnvConfig
    layers: list[LayerConfig] = Field(min_length=1)
    combine: CombineConfig = CombineConfig()
    learner: dict[str, Any] = {"kind": "td3"}
    """Learner settings shared by every layer (`kind` plus that learner's keys)."""
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
    log: LogConfig = LogConfig()

    def layer_names(self) -> list[str]:
        return [layer.name for layer in self.layers]

    def warmup(self, name: str) -> int:
        """Random decisions of layer `name` before it learns: its own `warmup`, else `train.warmup`."""
        own = self.layers[self.layer_names().index(name)].warmup
        return self.train.warmup if own is None else own

    def learner_config(self, index: int) -> LearnerConfig:
        """The validated learner settings of layer `index`: its own table over the shared one."""
        table = {"kind": "td3", **self.learner, **self.layers[index].learner}
        return LEARNERS.get(table["kind"]).Config.model_validate(table)

    def return_range(self) -> tuple[float, float] | None:
        """The (worst, best) return of an episode: the recipe's `env.return_range`, else the registry's."""
        return self.env.return_range or env_info(self.env.id).return_range

    def threshold(self, index: int) -> float:
        """The evaluation threshold (fraction of max action) applied below layer `index`."""
        own = self.layers[index].eval_threshold
        return own if own is not None else self.combine.eval_threshold


def _key(loc: Iterable[Any]) -> str:
    """`layers[1].period` from a pydantic location tuple."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _describe(error: Mapping[str, Any]) -> str:
    """A one-line account of a pydantic error: what was expected and what was given."""
    kind, msg = error["type"], error["msg"]
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "required key is missing"
    if kind == "value_error":  # a check across fields: its own words say what is wrong
        return str(error["ctx"]["error"])
    given = error.get("input")
    return f"{msg[0].lower()}{msg[1:]} (got {given!r})" if not isinstance(given, dict) else msg


def _check_stack(recipe: Recipe) -> list[tuple[str, str]]:
    """Problems no single field shows: names, periods, references, registries, learners, env."""
    problems = _check_layers(recipe) + _check_learners(recipe) + _check_training(recipe)
    if recipe.combine.kind not in COMBINERS:
        problems.append(("combine.kind", f"unknown combiner {recipe.combine.kind!r}; known: {', '.join(COMBINERS)}"))
    try:
        env_info(recipe.env.id)
    except KeyError as e:
        problems.append(("env.id", str(e.args[0])))
    return problems or _check_capabilities(recipe)


def _check_layers(recipe: Recipe) -> list[tuple[str, str]]:
    """Unique names, dividing periods, `sees` naming slower layers, known combiners."""
    problems: list[tuple[str, str]] = []
    names = recipe.layer_names()
    for i, layer in enumerate(recipe.layers):
        where = f"layers[{i}]"
        if names.index(layer.name) != i:
            problems.append((f"{where}.name", f"layer name {layer.name!r} is used twice"))
        above = recipe.layers[i - 1] if i else None
        if above is not None and above.period % layer.period:  # type: ignore[operator]  # resolved to ints
            problems.append((f"{where}.period", f"period {layer.period} does not divide the period {above.period} of "
                             f"layer {above.name!r} above it (layers are listed slowest first)"))
        problems += [(f"{where}.sees", f"{seen!r} is neither 'obs' nor a slower layer than {layer.name!r}")
                     for seen in layer.sees if seen != "obs" and seen not in names[:i]]
        if layer.combine is None:
            continue
        if layer.combine not in COMBINERS:
            problems.append((f"{where}.combine", f"unknown combiner {layer.combine!r}; known: {', '.join(COMBINERS)}"))
        elif i == len(names) - 1:
            problems.append((f"{where}.combine", "the fastest layer has no layer below to merge with; remove its "
                             "combine"))
    return problems


def _check_capabilities(recipe: Recipe) -> list[tuple[str, str]]:
    """The environment's spaces suit layers, and each layer's learner can drive what the layer outputs."""
    try:
        spaces = env_spaces(recipe.env.id)
    except KeyError as e:
        return [("env.id", str(e.args[0]))]
    if (problem := spaces.problem()) is not None:
        return [("env.id", f"{recipe.env.id} cannot be controlled by layers: {problem}")]
    action_dims = int(spaces.action_space.shape[0])  # type: ignore[index]  # a Box vector, checked above
    problems = []
    for i, layer in enumerate(recipe.layers):
        if layer.action_penalty_unit == "reward-per-step" and reward_per_step(recipe) is None:
            problems.append((f"layers[{i}].action_penalty_unit", f"{recipe.env.id} has no known return range and "
                             "episode length; give env.return_range, or the penalty in reward units"))
    for i, layer in enumerate(recipe.layers):
        if layer.learn_from_commits and (why := _cannot_learn_from_commits(recipe, i, action_dims)) is not None:
            problems.append((f"layers[{i}].learn_from_commits", why))
    for i in range(len(recipe.layers)):
        learner = LEARNERS.get(recipe.learner_config(i).kind)
        layout = output_layout(recipe, i, action_dims)
        if (why := learner.unfit(layout)) is not None:
            problems.append((f"layers[{i}].learner", f"learner {recipe.learner_config(i).kind!r} cannot drive layer "
                             f"{recipe.layers[i].name!r}, which outputs {layout.describe()}: {why}"))
    return problems


def _cannot_learn_from_commits(recipe: Recipe, i: int, action_dims: int) -> str | None:
    """Why layer i cannot take the executed action as its decision under a committed gate, if it cannot."""
    if i == 0 or not output_layout(recipe, i - 1, action_dims).gate_dims:
        return "only the layer right below a gate can learn from its commits"
    layer = recipe.layers[i]
    if layer.delay or layer.max_repeat > 1 or output_layout(recipe, i, action_dims).gate_dims:
        return ("the executed action must be a decision the layer could have taken: it needs delay 0, "
                "max_repeat 1 and no gate of its own")
    return None


def _check_learners(recipe: Recipe) -> list[tuple[str, str]]:
    """The shared [learner] table, then each layer's own table merged over it."""
    shared = _check_learner(recipe.learner)
    problems = [(f"learner{k}", m) for k, m in shared]
    for i, layer in enumerate(recipe.layers):  # a layer's own table can only break a valid shared one
        if layer.learner and not shared:
            merged = _check_learner({**recipe.learner, **layer.learner})
            problems += [(f"layers[{i}].learner{k}", m) for k, m in merged]
    return problems


def _check_training(recipe: Recipe) -> list[tuple[str, str]]:
    """A known order, and explicit phases that name existing layers."""
    problems: list[tuple[str, str]] = []
    names = recipe.layer_names()
    if recipe.train.order not in ORDERS:
        problems.append(("train.order", f"unknown order {recipe.train.order!r}; known: {', '.join(ORDERS)}"))
    elif recipe.train.order == "explicit" and not recipe.train.phases:
        problems.append(("train.phases", "the explicit order needs at least one [[train.phases]]"))
    elif recipe.train.phases and recipe.train.order in MAKE_OWN_PHASES:
        problems.append(("train.phases", f"the {recipe.train.order!r} order makes its own phases and would ignore "
                         "these; set train.order = \"explicit\" to use them"))
    for p, phase in enumerate(recipe.train.phases or []):
        for field in ("learn", "active"):
            problems += [(f"train.phases[{p}].{field}", f"no layer named {name!r}; layers: {', '.join(names)}")
                         for name in getattr(phase, field) or [] if name not in names]
    return problems


def _check_learner(table: dict[str, Any]) -> list[tuple[str, str]]:
    """Problems of one layer's merged learner table, keyed relative to it."""
    kind = table.get("kind", "td3")
    if kind not in LEARNERS:
        return [(".kind", f"unknown learner {kind!r}; known: {', '.join(LEARNERS)}")]
    try:
        LEARNERS.get(kind).Config.model_validate({**table, "kind": kind})
    except ValidationError as e:
        return [(f".{_key(err['loc'])}" if err["loc"] else "", _describe(err)) for err in e.errors()]
    return []


_PATH_PART = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def _parse_value(text: str) -> Any:
    """A TOML value (`3`, `1e-3`, `true`, `[1, 2]`, `"x"`); anything else is taken as a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_override(data: dict[str, Any], override: str) -> None:
    """Set one `key=value` override in the raw recipe table; layers may be named or indexed."""
    path, sep, text = override.partition("=")
    if not sep or not path.strip():
        raise RecipeError("command line", [(override, "an override is written key=value, e.g. train.seed=3")])
    parts = [m.group(1) or int(m.group(2)) for m in _PATH_PART.finditer(path.strip())]
    parts = [int(p) if isinstance(p, str) and p.isdigit() else p for p in parts]
    node: Any = data
    for depth, part in enumerate(parts[:-1]):
        node = _descend(node, part, parts[: depth + 1], override)
    last = parts[-1]
    if isinstance(node, list):
        node[_list_index(node, last, override)] = _parse_value(text)
    else:
        node[last] = _parse_value(text)


def _descend(node: Any, part: str | int, seen: list[str | int], override: str) -> Any:
    if isinstance(node, list):
        return node[_list_index(node, part, override)]
    if not isinstance(node, dict):
        raise RecipeError("command line", [(override, f"{_key(seen[:-1])} is a value, not a table")])
    return node.setdefault(str(part), {})


def _list_index(items: list[Any], part: str | int, override: str) -> int:
    """Index of a list entry given by position or, for layers and phases, by name."""
    if isinstance(part, int):
        if not -len(items) <= part < len(items):
            raise RecipeError("command line", [(override, f"index {part} is out of range (there are {len(items)})")])
        return part
    for i, item in enumerate(items):
        if isinstance(item, dict) and item.get("name") == part:
            return i
    raise RecipeError("command line", [(override, f"no entry named {part!r}")])


def load_recipe(source: str | Path | Mapping[str, Any], overrides: Iterable[str] = ()) -> Recipe:
    """The validated recipe from a TOML file or a table, with `key=value` overrides applied.

    Raises RecipeError, whose lines each name the file, the key and what was expected.
    """
    if isinstance(source, Mapping):
        label, data = "<recipe>", _deep_copy(dict(source))
    else:
        label, data = str(source), read_recipe_file(Path(source))
    overrides = list(overrides)
    for override in overrides:
        apply_override(data, override)
    _absolute_weights(data, Path.cwd())  # paths given on the command line are relative to where it runs
    if overrides:
        label += " (with command-line overrides)"
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as e:
        raise RecipeError(label, [(_key(err["loc"]), _describe(err)) for err in e.errors()]) from None
    recipe, problems = _resolve_periods(recipe)
    problems = problems or _check_stack(recipe)
    if problems:
        raise RecipeError(label, problems)
    return recipe


def _resolve_periods(recipe: Recipe) -> tuple[Recipe, list[tuple[str, str]]]:
    """Every layer's period in base steps, converting response times with the env's timestep."""
    problems: list[tuple[str, str]] = []
    dt: float | None = None
    layers = []
    for i, layer in enumerate(recipe.layers):
        if layer.response_time is None:
            if layer.period is None:
                problems.append((f"layers[{i}]", "give the layer a period (steps) or a response_time (seconds)"))
            layers.append(layer)
            continue
        if dt is None:
            try:
                dt = env_spaces(recipe.env.id).timestep
            except KeyError as e:
                return recipe, [("env.id", str(e.args[0]))]
            if dt is None:
                return recipe, [(f"layers[{i}].response_time",
                                 f"{recipe.env.id} defines no control timestep; give the period in steps")]
        steps = layer.response_time / dt
        if abs(steps - round(steps)) > 1e-6 * max(1.0, steps) or round(steps) < 1:
            problems.append((f"layers[{i}].response_time", f"{layer.response_time} s is not a whole number of "
                             f"the environment's {dt:g} s steps ({steps:.4g} steps)"))
        elif layer.period is not None and layer.period != round(steps):
            problems.append((f"layers[{i}].period", f"period {layer.period} disagrees with response_time "
                             f"{layer.response_time} s = {round(steps)} steps of {dt:g} s"))
        else:
            layer = layer.model_copy(update={"period": round(steps)})
        layers.append(layer)
    return recipe.model_copy(update={"layers": layers}), problems


def read_recipe_file(path: Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The raw table of a recipe file, merged over the file it `extends` (a path relative to it).

    Tables merge key by key; any other value, lists of layers included, replaces the base's.
    """
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecipeError(str(path), [("", "no such recipe file")]) from None
    except IsADirectoryError:
        raise RecipeError(str(path), [("", "is a directory, not a recipe file")]) from None
    except UnicodeDecodeError as e:
        raise RecipeError(str(path), [("", f"not UTF-8 text (byte {e.start}); a recipe is a TOML text file")]) from None
    except OSError as e:
        raise RecipeError(str(path), [("", f"cannot be read: {e.strerror or e}")]) from None
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(str(path), [("", f"not valid TOML: {e}")]) from None
    _absolute_weights(data, path.parent)
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise RecipeError(str(path), [("extends", f"expected the path of a recipe file (got {base!r})")])
    base_path = (path.parent / base).resolve()
    if base_path in _seen:
        raise RecipeError(str(path), [("extends", f"{base} extends itself through {', '.join(map(str, _seen))}")])
    return _merge(read_recipe_file(base_path, (*_seen, path.resolve())), data)


def _absolute_weights(data: dict[str, Any], base: Path) -> None:
    """Make each layer's `weights` path absolute, relative ones taken from `base`, so that a run's
    saved recipe names the same files wherever it is resumed from."""
    layers = data.get("layers")
    for layer in layers if isinstance(layers, list) else []:
        if isinstance(layer, dict) and isinstance(layer.get("weights"), str):
            layer["weights"] = str((base / layer["weights"]).resolve())


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _deep_copy(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: _deep_copy(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_deep_copy(v) for v in data]
    return data


def resolved(recipe: Recipe) -> dict[str, Any]:
    """The recipe as plain data with every default and each layer's full learner settings."""
    data = recipe.model_dump(mode="json", exclude_none=True)
    for i, layer in enumerate(data["layers"]):
        layer["learner"] = recipe.learner_config(i).model_dump(mode="json")
    return data
