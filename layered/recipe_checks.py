"""Checks of a recipe across its fields, run after the schema's: names, periods and references,
registries, learners against what their layers output, the environment's spaces."""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from layered.combiners import COMBINERS
from layered.envs import env_info, env_spaces
from layered.learners import LEARNERS
from layered.orders import MAKE_OWN_PHASES, ORDERS, phases_of
from layered.schema import DEFAULT_LEARNER, Recipe, describe_error, key_path


def check_recipe(recipe: Recipe) -> list[tuple[str, str]]:
    """Problems no single field shows: names, periods, references, registries, learners, env."""
    problems = _check_layers(recipe) + _check_learners(recipe) + _check_training(recipe)
    if recipe.combine.kind not in COMBINERS:
        problems.append(("combine.kind", COMBINERS.unknown(recipe.combine.kind)))
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
        if layer.action_penalty_from is not None and not layer.delay:
            problems.append((f"{where}.action_penalty_from", "without a delay an output acts from its decision on: "
                             "remove the key, or give the layer a delay"))
        if layer.sees_in_flight and not (layer.delay and set(layer.sees) - {"obs"}):
            problems.append((f"{where}.sees_in_flight", "it shows the slower layers in `sees` beside the layer's "
                             "outputs in flight: it needs a delay and a slower layer in `sees`"))
        if layer.max_repeat > 1 and layer.delay:
            problems.append((f"{where}.max_repeat", "a layer that chooses how long to hold its output takes no delay: "
                             "its count would hold the output already in flight, not the one it came with"))
        if layer.sees_executed and not layer.delay:
            problems.append((f"{where}.sees_executed", "without a delay a layer has no outputs in flight to see: "
                             "remove the key, or give the layer a delay"))
        problems += _unused_settings(recipe, i)
        if layer.combine is None:
            continue
        if layer.combine not in COMBINERS:
            problems.append((f"{where}.combine", COMBINERS.unknown(layer.combine)))
        elif i == len(names) - 1:
            problems.append((f"{where}.combine", "the fastest layer has no layer below to merge with; remove its "
                             "combine"))
    return problems


def _unused_settings(recipe: Recipe, i: int) -> list[tuple[str, str]]:
    """Layer `i`'s settings for a combiner it does not have: a gate's rewards while it defers on a layer that gates
    nothing, a threshold on one whose combiner thresholds nothing (the fastest layer, a gate)."""
    layer, kind = recipe.layers[i], recipe.combiner_kind(i)
    combiner = COMBINERS.get(kind) if kind is not None and kind in COMBINERS else None
    has = "it is the fastest layer" if kind is None else f"its combiner is {kind!r}"
    gates = bool(combiner and combiner.gate_dims)
    problems = [(f"layers[{i}].{key}", f"it shapes a gate's rewards while the gate defers, and layer {layer.name!r} "
                 f"gates nothing ({has}): remove the key")
                for key in ("defer_reward_scale", "defer_penalty")
                if not gates and getattr(layer, key) != type(layer).model_fields[key].default]
    if layer.eval_threshold is not None and not (combiner and combiner.thresholded):
        problems.append((f"layers[{i}].eval_threshold", "it thresholds the contributions this layer's combiner admits "
                         f"from the layer right below it, and layer {layer.name!r} thresholds none ({has}): remove "
                         "the key"))
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
        if layer.action_penalty_unit == "reward-per-step" and recipe.reward_per_step() is None:
            problems.append((f"layers[{i}].action_penalty_unit", f"{recipe.env.id} has no known return range and "
                             "episode length; give env.return_range, or the penalty in reward units"))
    for i, layer in enumerate(recipe.layers):
        if layer.learn_from_commits and (why := _cannot_learn_from_commits(recipe, i, action_dims)) is not None:
            problems.append((f"layers[{i}].learn_from_commits", why))
    for i in range(len(recipe.layers)):
        learner = LEARNERS.get(recipe.learner_config(i).kind)
        layout = recipe.output_layout(i, action_dims)
        if (why := learner.unfit(layout)) is not None:
            problems.append((f"layers[{i}].learner", f"learner {recipe.learner_config(i).kind!r} cannot drive layer "
                             f"{recipe.layers[i].name!r}, which outputs {layout.describe()}: {why}"))
    return problems


def _cannot_learn_from_commits(recipe: Recipe, i: int, action_dims: int) -> str | None:
    """Why layer i cannot take the executed action as its decision under a committed gate, if it cannot."""
    above = recipe.combiner_kind(i - 1) if i else None
    if above is None or COMBINERS.get(above).encoding is None:
        return "only the layer right below a gate can learn from its commits"
    layer = recipe.layers[i]
    if layer.delay or layer.max_repeat > 1 or recipe.output_layout(i, action_dims).gate_dims:
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
            problems += [(f"layers[{i}].learner{k}", m + _shared_note(recipe, i, k)) for k, m in merged]
    return problems


def _shared_note(recipe: Recipe, index: int, key: str) -> str:
    """Where a problem of layer `index`'s learner setting `key` (".hidden") came from the shared [learner] table: so."""
    name, top = recipe.layers[index].name, key.lstrip(".").split(".")[0]
    if top not in recipe.learner or top in recipe.layers[index].learner:
        return ""
    return (f" (layer {name!r} takes it from [learner], which every layer takes: set it only for the layers whose "
            f"learner has it, as layers.<name>.learner.{top})")


def _check_training(recipe: Recipe) -> list[tuple[str, str]]:
    """A known order; explicit phases that name existing layers, each present where it learns; and no layer
    present that never learns and is given no weights."""
    problems: list[tuple[str, str]] = []
    names = recipe.layer_names()
    if recipe.train.order not in ORDERS:
        problems.append(("train.order", ORDERS.unknown(recipe.train.order)))
    elif recipe.train.order == "explicit" and not recipe.train.phases:
        problems.append(("train.phases", "the explicit order needs at least one [[train.phases]]"))
    elif recipe.train.phases and recipe.train.order in MAKE_OWN_PHASES:
        problems.append(("train.phases", f"the {recipe.train.order!r} order makes its own phases and would ignore "
                         "these; set train.order = \"explicit\" to use them"))
    for p, phase in enumerate(recipe.train.phases or []):
        for field in ("learn", "active"):
            problems += [(f"train.phases[{p}].{field}", f"no layer named {name!r}; layers: {', '.join(names)}")
                         for name in getattr(phase, field) or [] if name not in names]
        if phase.active is not None and (absent := [n for n in phase.learn if n not in phase.active]):
            problems.append((f"train.phases[{p}].active", f"leaves out {', '.join(map(repr, absent))}, which "
                             f"{'learns' if len(absent) == 1 else 'learn'} in this phase: a layer learns where it is "
                             "present"))
    return problems or _untrained(recipe)


def _untrained(recipe: Recipe) -> list[tuple[str, str]]:
    """Layers present in a phase that learn in none and start from no `weights`: their random initial weights
    would act, and no checkpoint would hold them for `eval`, `export` or `report`."""
    phases = phases_of(recipe)
    learned = {name for phase in phases for name in phase.learn}
    key = "train.phases" if recipe.train.order == "explicit" else "train.order"
    first_present: dict[str, int] = {}
    for p, phase in enumerate(phases):
        for name in phase.active:
            first_present.setdefault(name, p)
    names = recipe.layer_names()
    return [(key, f"layer {name!r} is present in phase {p} but learns in no phase and starts from no "
             f"layers[{names.index(name)}].weights: give it weights, or a phase to learn in")
            for name, p in first_present.items()
            if name not in learned and recipe.layers[names.index(name)].weights is None]


def _check_learner(table: dict[str, Any]) -> list[tuple[str, str]]:
    """Problems of one layer's merged learner table, keyed relative to it."""
    kind = table.get("kind", DEFAULT_LEARNER)
    if kind not in LEARNERS:
        return [(".kind", LEARNERS.unknown(kind))]
    try:
        LEARNERS.get(kind).Config.model_validate({**table, "kind": kind})
    except ValidationError as e:
        return [(f".{key_path(err['loc'])}" if err["loc"] else "", describe_error(err)) for err in e.errors()]
    return []
