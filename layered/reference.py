"""The recipe reference in Markdown, generated from the schema so it cannot drift from it.

`python -m layered.reference > docs/recipe-reference.md` regenerates it; a test checks it.
"""

from __future__ import annotations

import json
import sys

from pydantic import BaseModel

from layered.learners import LEARNERS
from layered.schema import (
    CombineConfig,
    EnvConfig,
    EvalConfig,
    LayerConfig,
    LogConfig,
    PhaseConfig,
    Recipe,
    TrainConfig,
)

TABLES: list[tuple[str, type[BaseModel]]] = [
    ("[env]", EnvConfig), ("[[layers]]", LayerConfig), ("[combine]", CombineConfig),
    ("[train]", TrainConfig), ("[[train.phases]]", PhaseConfig), ("[eval]", EvalConfig), ("[log]", LogConfig),
]


def _default(model: type[BaseModel], name: str) -> str:
    field = model.model_fields[name]
    if field.is_required():
        return "required"
    return f"`{json.dumps(field.get_default(call_default_factory=True))}`"


def _table(title: str, model: type[BaseModel]) -> list[str]:
    lines = [f"## `{title}`", "", (model.__doc__ or "").strip(), "", "| key | default | meaning |", "|---|---|---|"]
    for name, field in model.model_fields.items():
        doc = " ".join((field.description or "").split()).replace("|", "\\|")
        lines.append(f"| `{name}` | {_default(model, name)} | {doc} |")
    return [*lines, ""]


def reference() -> str:
    """The whole reference: every recipe table, then every registered learner's settings."""
    lines = ["# Recipe reference", "", "Generated from the schema by `python -m layered.reference`; do not edit.", "",
             (Recipe.__doc__ or "").strip(), "",
             "`[learner]` holds settings shared by every layer's learner (`kind` plus that learner's keys); "
             "`[layers.learner]` overrides them for one layer.", "",
             "A top-level `extends = \"path.toml\"` (relative to the recipe's file) takes that recipe and lays this "
             "one over it: tables merge key by key, and any other value, the list of `[[layers]]` included, replaces "
             "the one it extends. On the command line, `key=value` sets any key below: a layer by name or index "
             "(`layers.fast.action_penalty=0.5`, `layers[1].period=2`), the value read as TOML and as a string "
             "where it is none (`'learner.hidden=[64, 64]'`, quoted for the shell).", ""]
    for title, model in TABLES:
        lines += _table(title, model)
    for name in LEARNERS.names():
        lines += _table(f"[learner] kind = \"{name}\"", LEARNERS.get(name).Config)
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(reference())
