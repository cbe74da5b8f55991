"""Command-line overrides of a recipe: `key=value`, with layers and phases named or indexed."""

from __future__ import annotations

import re
import tomllib
from collections.abc import Sequence
from typing import Any

from layered.schema import RecipeError, key_path


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
        raise RecipeError("command line", [(override, f"{key_path(seen[:-1])} is a value, not a table")])
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


def split_values(text: str) -> list[str]:
    """The values of `a,b,c`: split at the commas outside brackets, braces and quotes (`[32, 32]` is one)."""
    values, depth, quote, start = [], 0, "", 0
    for i, char in enumerate(text):
        if quote:
            quote = "" if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        elif char == "," and depth == 0:
            values.append(text[start:i])
            start = i + 1
    return [*values, text[start:]]


def grid(overrides: Sequence[str]) -> list[tuple[list[str], list[str]]]:
    """The setups that overrides span: each `key=a,b,c` is an axis of values, and every combination of
    one value per axis is a setup (the product, the first axis slowest). Per setup: all its overrides,
    and those of the axes (what names the setup; none when no key has several values), by key, each number as
    Python writes it (`setup_name`), so that the same setups written otherwise get the same names."""
    return [(chosen, setup_names(named)) for chosen, named in written_grid(overrides)]


def written_grid(overrides: Sequence[str]) -> list[tuple[list[str], list[str]]]:
    """`grid`, its setups named as the command line wrote them (how sweeps named their setups before)."""
    axes = []
    for override in overrides:
        key, sep, text = override.partition("=")
        values = list(dict.fromkeys(split_values(text))) if sep else [text]  # a value named twice is one setup
        axes.append([f"{key}={value.strip()}" if sep else override for value in values])
    setups: list[tuple[list[str], list[str]]] = [([], [])]
    for options in axes:
        varies = len(options) > 1
        setups = [([*chosen, option], named + [option] * varies) for chosen, named in setups for option in options]
    return setups


def setup_names(options: Sequence[str]) -> list[str]:
    """A setup's `key=value`s as `grid` names them: by key, each as `setup_name` writes it."""
    return sorted(setup_name(option) for option in options)


def setup_name(option: str) -> str:
    """`key=value` with the key stripped and a number written as Python writes it (`0.50` and `5e-1`: `0.5`)."""
    key, _, text = option.partition("=")
    value = _parse_value(text)
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return f"{key.strip()}={value!r}" if number else f"{key.strip()}={text.strip()}"
