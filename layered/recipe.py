"""Loading recipes: TOML files (merged over the files they `extend`) or tables, with command-line
overrides, validated by the schema and the checks across fields, periods given in seconds resolved."""

from __future__ import annotations

import difflib
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from layered.envs import env_spaces
from layered.overrides import apply_override
from layered.recipe_checks import check_recipe
from layered.schema import Recipe, RecipeError, describe_error, key_path

__all__ = ["Recipe", "RecipeError", "load_recipe", "read_recipe_file", "resolved"]


def shipped_recipes() -> Path:
    """The folder of the recipes that ship with layered: inside the installed package, or the checkout's."""
    inside = Path(__file__).resolve().parent / "recipes"
    return inside if inside.is_dir() else inside.parent.parent / "recipes"


def recipe_path(source: str | Path) -> Path:
    """A recipe file: `source` itself where it exists, else the shipped recipe it names (`pendulum/tla-c`
    for recipes/pendulum/tla-c.toml), else `source` (which then reads as missing)."""
    path = Path(source)
    if path.exists() or path.is_absolute():
        return path
    shipped = shipped_recipes() / _as_toml(path)
    return shipped if shipped.is_file() else path


def _as_toml(path: Path) -> Path:
    """`path` with `.toml` added where it is not its suffix already (`hopper/td3.v2` is hopper/td3.v2.toml)."""
    return path if path.suffix == ".toml" else path.with_name(path.name + ".toml")


def load_recipe(source: str | Path | Mapping[str, Any], overrides: Iterable[str] = ()) -> Recipe:
    """The validated recipe from a TOML file (or the shipped recipe it names, see `recipe_path`) or a
    table, with `key=value` overrides applied.

    Raises RecipeError, whose lines each name the file, the key and what was expected.
    """
    overrides = list(overrides)
    label = recipe_label(source, overrides)
    data = _deep_copy(dict(source)) if isinstance(source, Mapping) else read_recipe_file(recipe_path(source))
    for override in overrides:
        apply_override(data, override)
    _absolute_weights(data, Path.cwd())  # paths given on the command line are relative to where it runs
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as e:
        raise RecipeError(label, [(key_path(err["loc"]), describe_error(err)) for err in e.errors()]) from None
    recipe, problems = _resolve_periods(recipe)
    problems = problems or check_recipe(recipe)
    if problems:
        raise RecipeError(label, problems)
    return recipe


def device_settings(source: str | Path, overrides: Sequence[str], device: str) -> list[str]:
    """`--device`: `layers.<name>.learner.device=<device>` for each layer whose learner has a device setting (a
    plugin's may have none, and the shared `learner.device` would then be refused for its layer)."""
    recipe = load_recipe(source, overrides)
    names = [layer.name for i, layer in enumerate(recipe.layers)
             if "device" in type(recipe.learner_config(i)).model_fields]
    if not names:
        raise RecipeError(recipe_label(source, overrides),
                          [(None, f"--device {device}: no layer's learner has a device setting")])
    return [f"layers.{name}.learner.device={device}" for name in names]


def recipe_label(source: str | Path | Mapping[str, Any], overrides: Sequence[str] = ()) -> str:
    """How errors name a recipe: its file (`<recipe>` for a table), and whether the command line changed it."""
    label = "<recipe>" if isinstance(source, Mapping) else str(source)
    return label + (" (with command-line overrides)" if overrides else "")


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
        raise RecipeError(str(path), [(None, f"no such recipe file{_shipped_like(path)}")]) from None
    except IsADirectoryError:
        raise RecipeError(str(path), [(None, "is a directory, not a recipe file")]) from None
    except UnicodeDecodeError as e:
        message = f"not UTF-8 text (byte {e.start}); a recipe is a TOML text file"
        raise RecipeError(str(path), [(None, message)]) from None
    except OSError as e:
        raise RecipeError(str(path), [(None, f"cannot be read: {e.strerror or e}")]) from None
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(str(path), [(None, f"not valid TOML: {e}")]) from None
    _absolute_weights(data, path.parent)
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise RecipeError(str(path), [("extends", f"expected the path of a recipe file (got {base!r})")])
    base_path = (path.parent / base).resolve()
    if base_path in _seen:
        raise RecipeError(str(path), [("extends", f"{base} extends itself through {', '.join(map(str, _seen))}")])
    if not base_path.exists():
        raise RecipeError(str(path), [("extends", f"no such recipe file: {base_path}")])
    return _merge(read_recipe_file(base_path, (*_seen, path.resolve())), data)


def _shipped_like(path: Path) -> str:
    """The shipped recipes whose names are closest to a missing `path` given by name, as the end of its message."""
    if path.is_absolute():
        return ""
    root = shipped_recipes()
    names = sorted(p.relative_to(root).with_suffix("").as_posix() for p in root.rglob("*.toml"))
    close = difflib.get_close_matches(_as_toml(path).with_suffix("").as_posix(), names, n=3, cutoff=0.6)
    return f"; shipped recipes with a name like it: {', '.join(close)}" if close else ""


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
